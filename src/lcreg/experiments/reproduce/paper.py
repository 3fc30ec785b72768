"""The paper's numbers that ``lcreg reproduce`` sets beside ours, transcribed from ``dvds-paper.tex``.

Every value is the paper's, to the digits printed there (full ModelNet40, NVIDIA Titan Xp). Rotation errors are in
degrees (DCP's Euler-angle RMSE/MAE, the ``rmse_r_deg``/``mae_r_deg`` of :mod:`lcreg.metrics`), translation errors in
the units of the unit-sphere clouds. A printed ``0.000`` is a value below 0.0005, not zero: ratios to it are not
shown.
"""

from __future__ import annotations

from collections.abc import Mapping

__all__ = ["ABLATION", "LC_PLUS_X", "PAPER_METRICS", "RUNTIME_MACHINE", "RUNTIME_MS", "RUNTIME_POINTS", "PaperTable"]

PAPER_METRICS = ("rmse_r_deg", "mae_r_deg", "rmse_t", "mae_t")
"""The columns of both tables, in the paper's order: RMSE(R), MAE(R), RMSE(t), MAE(t)."""

PaperTable = Mapping[str, Mapping[str, float]]
"""Rows of a paper table by name: metric (:data:`PAPER_METRICS`) -> value."""


def _rows(rows: Mapping[str, tuple[float, float, float, float]]) -> dict[str, dict[str, float]]:
    return {name: dict(zip(PAPER_METRICS, values)) for name, values in rows.items()}


# Table "Ablation studies of the proposed model" (\label{ablation_all}): DVDs on the test set of the first 20
# categories of ModelNet40. The |X1| = 64 and (λ1, λ2) = (0.5, 0.1) rows repeat model D.
ABLATION: PaperTable = _rows(
    {
        "A": (4.201, 0.525, 0.023, 0.002),
        "B": (2.119, 0.250, 0.013, 0.002),
        "C": (1.620, 0.132, 0.008, 0.000),
        "D": (1.095, 0.101, 0.007, 0.000),
        "|X1| = 32": (2.008, 0.206, 0.012, 0.001),
        "|X1| = 64": (1.095, 0.101, 0.007, 0.000),
        "|X1| = 96": (2.424, 0.260, 0.013, 0.001),
        "λ1 = 0.5, λ2 = 0.5": (1.793, 0.193, 0.011, 0.001),
        "λ1 = 1, λ2 = 0.1": (1.747, 0.174, 0.009, 0.000),
        "λ1 = 0.5, λ2 = 0.1": (1.095, 0.101, 0.007, 0.000),
    }
)
"""The paper's ablation table (models A-D, |X1|, (λ1, λ2))."""

# Table "Local consistency loss can be integrated into various point cloud registration models" (\label{table4}).
# Its caption says trained and tested on the first 20 categories (the test set of those categories); the text of
# Section "Generality of Local Consistency Loss" says tested on the other 20 categories.
LC_PLUS_X: PaperTable = _rows(
    {
        "DCP": (4.834, 2.795, 0.020, 0.010),
        "PRNet": (1.506, 0.874, 0.015, 0.010),
        "IDAM": (2.084, 1.122, 0.022, 0.014),
        "DeepGMR": (3.472, 1.526, 0.004, 0.001),
        "LC + DCP": (3.950, 2.298, 0.020, 0.010),
        "LC + PRNet": (1.293, 0.783, 0.014, 0.010),
        "LC + IDAM": (1.527, 0.933, 0.016, 0.010),
        "LC + DeepGMR": (3.192, 1.247, 0.004, 0.001),
    }
)
"""The paper's LC + X table (four hosts without and with local consistency)."""

# Table "Running time comparisons for registering a point cloud pair (in milliseconds)" (\label{table3}), rows in the
# paper's order, by registry key. Section "Efficiency": test pairs of the last 20 categories of ModelNet40 with
# Gaussian noise; ICP, FGR and RANSAC run on the CPU, the learned methods on the GPU.
RUNTIME_POINTS = (500, 1000, 2000)
"""Points per cloud of the runtime table's columns."""
RUNTIME_MS: Mapping[str, tuple[float, float, float]] = {
    "icp": (7, 16, 35),
    "pointnetlk": (70, 73, 75),
    "dcp": (6, 9, 20),
    "fgr": (143, 172, 232),
    "ransac": (18, 48, 110),
    "fmr": (68, 70, 72),
    "pcrnet": (14, 16, 18),
    "dvds": (66, 68, 69),
}
"""The paper's ms per pair at :data:`RUNTIME_POINTS` by method (``"dvds"`` is the paper's "Ours")."""
RUNTIME_MACHINE = "2.10 GHz Intel Xeon E5-2620 (ICP, FGR, RANSAC) and NVIDIA Titan Xp (learned methods)"
"""Where the paper's runtime table was measured (Section "Efficiency")."""
