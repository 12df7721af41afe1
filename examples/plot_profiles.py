"""Example: compare the dipole and Burley profiles of a preset, and the lookup-table speed path.

Run: ``python examples/plot_profiles.py --material skin1 --out out/example_profiles.png``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

import torchsss
from torchsss.physics import lookup_profile_table, profile_table_error


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--material", default="skin1")
    parser.add_argument("--out", type=Path, default=Path("out/example_profiles.png"))
    args = parser.parse_args()

    dipole = torchsss.DipoleMaterial.from_preset(args.material, dtype=torch.float64)
    burley = torchsss.BurleyMaterial.from_preset(args.material, dtype=torch.float64)
    table = dipole.table(size=1024, eps=0.01)
    err = profile_table_error(table, dipole)
    print(f"{args.material}: R_total {dipole.total_diffuse_reflectance().tolist()}")
    print(f"r_max (eps=0.01) {table.r_max.tolist()} mm; LUT max relative error {err.tolist()}")

    r = torch.linspace(0, float(table.r_max.max()), 400, dtype=torch.float64).unsqueeze(-1)
    with torch.no_grad():
        curves = {"dipole": dipole(r), "burley": burley(r), "LUT (1024)": lookup_profile_table(r, table)}
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    styles = {"dipole": "-", "burley": "--", "LUT (1024)": ":"}
    for label, val in curves.items():
        for c, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
            ax.semilogy(r.squeeze(-1), val[:, c].clamp_min(1e-12), styles[label], color=colour,
                        label=label if c == 0 else None)
    ax.set_xlabel("r (mm)")
    ax.set_ylabel("R(r) (mm$^{-2}$)")
    ax.set_title(f"{args.material}: dipole vs Burley (same albedo)")
    ax.legend()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
