#!/usr/bin/env python3
"""Markdown tables from bench/results/hand/*.json (written by scripts/bench-hand)."""
import glob
import json
import os
import sys

out = sys.argv[1]
rows = {os.path.basename(p)[:-5]: json.load(open(p)) for p in sorted(glob.glob(os.path.join(out, "*.json")))}
if not rows:
    sys.exit("no results in " + out)
any_row = next(iter(rows.values()))
m = any_row["machine"]
print(f"Machine: {m['cpu']}, {m['cores']} cores, one thread used; BLAS `{os.path.basename(m['blas'])}`; "
      f"revision {m['git_revision']}. Command: `scripts/bench-hand` (hand pressed into a floor, dt = "
      f"{1000 * any_row['dt_s']:.1f} ms).\n")


def table(title, names, baseline=None):
    print(f"**{title}**\n")
    print("| tets | nodes | handles | solver | step median ms | step p99 ms | assembly | factor | Schur | solve "
          "| iterations (median) | refactors | rel. error vs monolithic | speed-up vs Schur+CG |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for n in names:
        if n not in rows:
            continue
        r = rows[n]
        base = rows.get(baseline(n)) if baseline else None
        speedup = f"{base['step_ms_median'] / r['step_ms_median']:.1f}x" if base else ""
        label = {"lagged": "Schur + lagged CHOLMOD (GMRES)", "cholmod": "Schur + CHOLMOD per step",
                 "cg": "Schur + CG (paper)", "monolithic": "monolithic sparse LU"}[r["solver"]]
        if "refblas" in n:
            label += ", reference BLAS"
        elif r["solver"] == "cholmod" and n.endswith(("_amd", "_metis", "_nesdis")):
            label += f", {r['ordering']} ordering"
        err = "reference" if r["solver"] == "monolithic" else f"{r['rel_error_vs_monolithic']:.1e}"
        if r["solver"] != "monolithic" and r["error_samples"] == 0:
            err = "not sampled"
        refactors = f"{r['factorizations']}/{r['steps']}" if r["solver"] in ("lagged", "cholmod") else ""
        iters = f"{r['iterations_median']:.0f}" if r["solver"] in ("lagged", "cg") else ""
        print(f"| {r['tets']} | {r['nodes']} | {r['handles']} | {label} | {r['step_ms_median']:.2f} | "
              f"{r['step_ms_p99']:.2f} | {r['assembly_ms']:.2f} | {r['factor_ms']:.2f} | {r['schur_ms']:.2f} | "
              f"{r['solve_ms']:.2f} | {iters} | {refactors} | {err} | {speedup} |")
    print()


sizes = sorted({r["tets"] for r in rows.values()})
names = []
for n in sorted(rows, key=lambda k: (rows[k]["tets"], rows[k]["handles"], k)):
    if rows[n]["handles"] == 1 and n.count("_") == 1:
        names.append(n)
table("One handle (stylus): solvers side by side, same run", names,
      lambda n: n.rsplit("_", 1)[0] + "_cg")
table("16 handles (palm + 15 phalanges) on the 1.7k-tet hand", [n for n in rows if "_m16_" in n],
      lambda n: n.rsplit("_", 1)[0] + "_cg")
table("Factorization at the largest size: orderings and BLAS", [n for n in rows if n.count("_") == 2 and "_m16_" not in n])
