"""field-15k: where the far bins' excess over the plane comes from (study.py's cache and
variants.py's). Usage: analyse.py SCENE"""
import sys

import numpy as np

LABELS = {1: "ground", 2: "facade", 3: "balcony", 4: "pole", 5: "car", 6: "window/passage",
          7: "object", 8: "van"}
name = sys.argv[1]
d = dict(np.load(f"out/s15k/{name}.npz"))
v = dict(np.load(f"out/s15k/{name}_variants.npz"))
y, dist = d["y"], d["dist"]
BINS = (0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 1.0, 2.0)
b = np.digitize(dist, BINS) - 1
cen, lab = d["closest_centroid"], d["label"]
COLS = [("map", d["mean"]), ("far", d["m_far"]), ("GP", d["m_gp"]),
        ("k 8", v["map normals, k 8"]), ("PCA16 k16", v["PCA16 normals, k 16"]),
        ("plane", d["plane"])]


def rmse(m, s):
    return 1000 * np.sqrt(np.mean((m[s] - y[s]) ** 2)) if s.sum() else np.nan


cat = np.array([LABELS.get(int(c), str(c)) for c in lab], dtype=object)
if name == "courtyard":  # field_scenes._courtyard's parts from the exact closest face
    x_, y_ = cen[:, 0], cen[:, 1]
    cat[(lab == 2) & (y_ > 2.5)] = "building front"
    cat[lab == 6] = "passage"
    cat[(lab == 2) & (y_ < -2.9) & (y_ > -3.3)] = "thin wall (gap)"
    cat[(lab == 2) & (y_ < -4.9)] = "corridor wall"
    cat[lab == 4] = "pillar"
    cat[(lab == 7) & (x_ < 11)] = "fence"
    cat[(lab == 7) & (x_ > 20)] = "kiosk"
cats = list(dict.fromkeys(cat))
print(f"## {name}\n\nRMSE (mm) by the category of the exact closest face; 'excess' is the "
      "category's share of the bin's sum of (map error^2 - plane error^2)")
for i in range(2, 5):
    s = b == i
    e2 = (d["mean"] - y) ** 2 - (d["plane"] - y) ** 2
    ex = e2[s].sum()
    print(f"\n**bin {BINS[i]}-{BINS[i + 1]} m** (n {s.sum()}; map - plane summed "
          f"{ex * 1e3:+.1f} e-3 m^2)\n")
    print("| category | n | " + " | ".join(c for c, _ in COLS) + " | excess share |")
    print("|---|---|" + "---|" * len(COLS) + "---|")
    for c in cats + ["all"]:
        k = s & (cat == c) if c != "all" else s
        if k.sum() < 10:
            continue
        print(f"| {c} | {k.sum()} | " + " | ".join(f"{rmse(m, k):.1f}" for _, m in COLS)
              + f" | {e2[k].sum() / ex:+.2f} |")
    a_m, a_p = np.abs(d["mean"] - y)[s], np.abs(d["plane"] - y)[s]
    big = np.maximum(a_m, a_p)
    keep = big <= np.quantile(big, 0.99)
    print(f"\nmedian |error| map {1e3 * np.median(a_m):.1f} / plane {1e3 * np.median(a_p):.1f} mm;"
          f" map closer to the truth than the plane for {np.mean(a_m < a_p):.2f} of the queries;"
          f" without the 1 % largest errors (either method) RMSE map "
          f"{1e3 * np.sqrt(np.mean(a_m[keep] ** 2)):.1f} / plane "
          f"{1e3 * np.sqrt(np.mean(a_p[keep] ** 2)):.1f} mm; that 1 % carries "
          f"{(a_m[~keep] ** 2).sum() / (a_m ** 2).sum():.2f} of the map's squared error")
w = (d["mean"] - d["m_far"]) / np.where(np.abs(d["m_gp"] - d["m_far"]) > 1e-12,
                                        d["m_gp"] - d["m_far"], np.inf)
print("\nGP weight in the map's mean, median per bin:",
      " ".join(f"{np.median(w[b == i]):.4f}" for i in range(7)))
print("\nthe far field's k = 16 neighbours: distance of the 16th / of the nearest from the "
      "query (m), median per bin:",
      " ".join(f"{np.median(d['patch_radius'][b == i]):.3f} / {np.median(d['r'][b == i]):.3f}"
               for i in range(7)))
print(f"\nh (far.kernel_floor) {float(d['h']):.4f} m")
