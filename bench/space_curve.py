"""The spatial share's curve over the clouds of an `eval --space` run: means over the clouds of CD and HD
relative to the voxel grid's, the entropy gain relative to PRISM's (per cloud, and pooled: the gains summed
over the clouds against PRISM's, which a cloud where PRISM's own gain is near 0 or negative cannot swing),
and on how many clouds a share is worse than Random (CD by more than 5%, or any gain).

    prism-stream eval tests/data/real/* --ratio 0.01,0.1 --space 0.25,0.5,0.75,0.8,0.9,1 \\
        --entropy-bins rgb-grid,rgb8,hue-sat --out docs/eval/space.json --out docs/eval/space.md
    python bench/space_curve.py docs/eval/space.json
"""

from __future__ import annotations

import json
import sys

import numpy as np


def main(path: str) -> None:
    rows = [r for r in json.load(open(path))["table"] if r["table"] == "main"]
    for ratio in sorted({r["target_ratio"] for r in rows}):
        rs = [r for r in rows if r["target_ratio"] == ratio]
        clouds = sorted({r["dataset"] for r in rs})

        def get(cloud, method, space=None):
            for r in rs:
                if r["dataset"] == cloud and r["method"].startswith(method) and (
                        method != "PRISM" or r["params"].get("space") == space):
                    return r
            raise KeyError((cloud, method, space))

        shares = sorted({r["params"].get("space") for r in rs if r["method"].startswith("PRISM")} - {None}, key=float)
        print(f"\nratio {ratio:g} ({len(clouds)} clouds; the gain is the headline entropy's)")
        print(f"{'method':<10} {'CD/V':>6} {'HD/V':>6} {'gain/P':>7} {'pooled':>7} {'CD/V max':>8} {'HD/V max':>8} "
              f"{'CD > 1.05 R':>11} {'gain < R':>8}")
        for label, method, space in [("PRISM", "PRISM", None)] + [(f"A = {a}", "PRISM", a) for a in shares] + [
                ("Random", "Random", None), ("Voxel", "Voxel", None), ("NSS", "NSS", None)]:
            cd, hd, gp, g, p, worse_cd, worse_g = [], [], [], [], [], 0, 0
            for c in clouds:
                prism, voxel, rnd, x = get(c, "PRISM"), get(c, "Voxel"), get(c, "Random"), get(c, method, space)
                cd.append(x["chamfer"] / voxel["chamfer"])
                hd.append(x["hausdorff"] / voxel["hausdorff"])
                gp.append(x["entropy_gain"] / prism["entropy_gain"])
                g.append(x["entropy_gain"])
                p.append(prism["entropy_gain"])
                worse_cd += x["chamfer"] > 1.05 * rnd["chamfer"]
                worse_g += x["entropy_gain"] < rnd["entropy_gain"]
            print(f"{label:<10} {np.mean(cd):6.3f} {np.mean(hd):6.3f} {np.mean(gp):7.3f} {sum(g) / sum(p):7.3f} "
                  f"{max(cd):8.3f} {max(hd):8.3f} {worse_cd:>11} {worse_g:>8}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "docs/eval/space.json")
