"""Study for docs/phonons.md (issue 17): dispersion of the demo crystal (the 2D crystal of
``affinebody demo`` in a periodic box) for d'Alembert vs af-is internal kinetic energy, and how
the affine pair term 0.5 exp(-D^2/4) (M1 - 2)^2 opens and mixes the internal branches.

Writes docs/figures/phonons_kinetic.png, phonons_affine_term.png, phonons_morse_in_d.png and
prints the
numbers quoted in docs/phonons.md. Run:
OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/phonons_study.py
"""

from __future__ import annotations

from pathlib import Path

CONFIG = """
[system]
n = 2
bodies = 16
box = [4.0, 4.0]

[body]
mass = 1.0
radius = 0.35

[kinetic]
{kinetic}

[[potential]]
kind = "morse"
depth = 1.0
alpha = 3.0
r0 = 1.0
r_cut = 1.5
{argument}{affine}
[[potential]]
kind = "dilatation"
stiffness = 5.0

[[potential]]
kind = "elastic"
lam = 0.5
mu = 1.0

[initial]
generator = "lattice"
spacing = 1.0

[run]
dt = 0.005
steps = 1

[phonons]
relax = true
points = 60
mesh = [24, 24]
"""
AF_IS = 'internal = "af-is"\nI = 0.5\nA = 0.1\nB = 0.05'
DALEMBERT = 'internal = "dalembert"'
AFFINE = ('\n[[potential]]\nkind = "pair"\nexpr = "0.5 * exp(-D**2 / 4) * (M1 - 2)**2"\n'
          'r_cut = 1.5\n')
MORSE_IN_D = 'argument = "D"\ncutoff_on = "r"\n'
FIGURES = Path(__file__).resolve().parents[1] / "docs" / "figures"


def document(kinetic: str, affine: str, argument: str = "") -> dict:
    from affinebody.cli.phonons import compute
    from affinebody.config import build, check_config, parse_config

    text = CONFIG.format(kinetic=kinetic, affine=affine, argument=argument)
    config = check_config(parse_config(text))
    return compute(config, build(config))


def panel(ax, doc, title):
    import numpy as np

    distance, omega = np.asarray(doc["distance"]), np.asarray(doc["omega"])
    internal = 1 - np.asarray(doc["character"]["shares"])[..., 0]
    for b in range(omega.shape[1]):
        ax.scatter(distance, omega[:, b], c=internal[:, b], s=3, cmap="coolwarm", vmin=0, vmax=1)
    ax.set_xticks([d for _, d in doc["ticks"]])
    ax.set_xticklabels(["Γ" if t == "G" else t for t, _ in doc["ticks"]])
    for _, d in doc["ticks"]:
        ax.axvline(d, color="0.85", lw=0.5)
    ax.axhline(0, color="0.6", lw=0.5)
    ax.set_xlim(distance[0], distance[-1])
    ax.set_title(title, fontsize=9)


def summary(name, doc):
    import numpy as np

    omega = np.asarray(doc["omega"])
    shares = np.asarray(doc["character"]["shares"])
    gamma = omega[0]
    speeds = doc["sound_speeds"]
    c = np.asarray(doc["elastic_constants"]["voigt"])
    mixing = float(np.max(np.minimum(shares[..., 0], 1 - shares[..., 0])))
    width = [float(omega[:, b].max() - omega[:, b].min()) for b in range(2, omega.shape[1])]
    print(f"{name}: omega(Gamma) = {np.round(gamma, 4).tolist()}; internal bandwidths "
          f"{np.round(width, 4).tolist()}; largest translational/internal mixing {mixing:.3f}; "
          f"imaginary on the path {doc['imaginary']}; sound speeds [100] "
          f"{np.round(speeds[0]['speeds'], 4).tolist()}, [110] "
          f"{np.round(speeds[2]['speeds'], 4).tolist()}; C11 C12 C66 = {c[0, 0]:.4f} "
          f"{c[0, 1]:.4f} {c[2, 2]:.4f} (fit residual "
          f"{doc['elastic_constants']['fit_residual']:.1e})"
          f"; residual force after relaxing {doc['crystal']['residual_force']:.1e}")


def main() -> None:
    from affinebody._checks import enable_x64

    enable_x64()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    docs = {
        "d'Alembert, with the affine pair term": document(DALEMBERT, AFFINE),
        "af-is (I, A, B) = (0.5, 0.1, 0.05), with the affine pair term": document(AF_IS, AFFINE),
        "af-is, without the affine pair term": document(AF_IS, ""),
        "af-is, with the affine pair term and Morse in D": document(AF_IS, AFFINE, MORSE_IN_D),
    }
    for name, doc in docs.items():
        summary(name, doc)
    names = list(docs)
    for pair, file, share in (((0, 1), "phonons_kinetic.png", False),
                              ((2, 1), "phonons_affine_term.png", True),
                              ((1, 3), "phonons_morse_in_d.png", True)):
        fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=share)
        for ax, index in zip(axes, pair, strict=True):
            panel(ax, docs[names[index]], names[index])
        axes[0].set_ylabel("ω")
        fig.tight_layout()
        fig.savefig(FIGURES / file, dpi=120)

if __name__ == "__main__":
    main()
