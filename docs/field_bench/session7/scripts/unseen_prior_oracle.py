import sys, json
sys.path.insert(0,"scripts")
from pathlib import Path
import numpy as np, fit_variance as FV
from gmmgp_app.stages.unseen import UnseenMixture
basej = {r["scene"]: r["methods"] for r in json.loads(Path("docs/field_bench/bench_accuracy.json").read_text())["results"]}
TWO=FV.TWO_SIGMA
grid=[0.0075,0.03,0.0675,0.15,0.3,0.5]
def score(d, qb, qe):
    t=FV.terms(d); v=t["ll"]+t["kap"]
    m=d["mean"]; y=d["y"]
    hw1=np.sqrt(v); hw2=2*np.sqrt(v); ll=-0.5*np.log(2*np.pi*v)-0.5*(y-m)**2/v
    for q,sel in ((qb, m<0),(qe, m>=0)):
        s=sel&((t["w_b"]>0)|(t["w_e"]>0))
        mix=UnseenMixture(m[s], v[s], t["w_b"][s], t["w_e"][s], np.sqrt(q/3))
        hw1[s]=mix.half_width(0.6826894921370859); hw2[s]=mix.half_width(TWO); ll[s]=mix.logpdf(y[s])
    e=np.abs(y-m); c1=[];c2=[];L=[]
    for i in range(7):
        s=d["bin"]==i; c1.append(np.mean(e[s]<=hw1[s])); c2.append(np.mean(e[s]<=hw2[s])); L.append(ll[s].mean())
    return c1,c2,L
names=sys.argv[1].split(",")
for n in names:
    d=FV.scene_case(n,0,Path("out/calib"))
    best=[]
    for qb in grid:
        for qe in grid:
            c1,c2,L=score(d,qb,qe)
            n1=sum(abs(round(c,2)-0.68)<=0.05+1e-9 for c in c1); n2=sum(abs(round(c,2)-0.95)<=0.03+1e-9 for c in c2)
            nl=sum(L[i]>FV.best_baseline_ll(basej[n],i) for i in range(7)) if n in basej else 0
            best.append((n1+n2+nl,n1,n2,nl,qb,qe," ".join(f"{c:.2f}" for c in c1[4:]), " ".join(f"{c:.2f}" for c in c2[4:])))
    best.sort(key=lambda x:-x[0])
    base=[b for b in best if b[4]==0.0675 and b[5]==0.0675][0]
    print(n, "default", base[1:4], base[6], "|", base[7])
    for b in best[:4]: print("   qb",b[4],"qe",b[5],"bins",b[1:4], "1s far", b[6], "| 2s far", b[7])
