"""field-15k: where the map's normals on the courtyard's high facade (z > 3 m) are more than 10
degrees off: their neighbour count within normal_radius (0.2216 m) against the good ones'."""
import sys; sys.path.insert(0,"scripts")
import numpy as np
from scipy.spatial import cKDTree
import bench_accuracy as B
d = dict(np.load("out/s15k/courtyard.npz")); P,N=d["far_points"],d["far_normals"]
scene=B.make_scan("courtyard",0.3,0)[1]
_,tri,_=scene.distance(P,return_closest=True); V=scene.vertices[scene.faces[tri]]
nt=np.cross(V[:,1]-V[:,0],V[:,2]-V[:,0]); nt/=np.linalg.norm(nt,axis=1,keepdims=True)
a=np.degrees(np.arccos(np.clip(np.abs((N*nt).sum(1)),0,1)))
hf=(scene.face_labels[tri]==2)&(P[:,1]>2.5)&(P[:,2]>3)
cnt=cKDTree(P).query_ball_point(P,0.2216,return_length=True,workers=-1)
bad=hf&(a>10); good=hf&(a<2)
print("bad",bad.sum(),"good",good.sum())
for lab,s in (("bad",bad),("good",good)):
    print(lab,"z median",np.median(P[s,2]),"count in R median",np.median(cnt[s]),"p10",np.quantile(cnt[s],.1),"x quantiles",np.quantile(P[s,0],[.1,.5,.9]).round(1))
print("bad normal median components", np.median(np.abs(N[bad]),0).round(2))
