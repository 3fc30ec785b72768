"""The LC + X experiment's own pieces: the LC-matched variants and the size of the LC term in the report."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest

from lcreg.experiments.reproduce.lc import LC, lc_share_lines
from lcreg.experiments.reproduce.spec import Variant


@pytest.mark.parametrize("host", ["idam", "dcp"])
def test_a_matched_variant_is_its_lc_host_with_only_the_lc_weight_changed(host: str) -> None:
    """``<host>/LC-matched`` builds ``<host>_lc`` (``configs/lc.yaml``) with the LC weight of MATCHED_LC_WEIGHTS."""
    from lcreg.experiments.benchmarking import build_cli_for, synthetic_overrides
    from lcreg.experiments.reproduce.lc import MATCHED_LC_WEIGHTS

    def lc_term(variant: Variant) -> tuple[float, dict[str, object]]:
        model = build_cli_for(variant.method, (), {**synthetic_overrides(), **copy.deepcopy(variant.overrides)}).model
        (term,) = model.loss_terms
        public = {k: v for k, v in vars(term.local_consistency).items() if not k.startswith("_")}
        return term.weight, public

    weight, matched = lc_term(LC.variant(f"{host}/LC-matched"))
    paper_weight, literal = lc_term(LC.variant(f"{host}/LC"))
    assert (weight, paper_weight) == (MATCHED_LC_WEIGHTS[host], 1.0) and matched == literal
    assert LC.variant(f"{host}/LC-matched").method == LC.variant(f"{host}/LC").method == f"{host}_lc"


def _metrics(folder: Path, name: str, rows: list[tuple[int, float, float]]) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["step,train/lc_step,train/loss_step", *(f"{s},{lc},{loss}" for s, lc, loss in rows)]
    (folder / name).write_text("\n".join(lines) + "\n")
    return folder / "metrics.csv"


def test_the_lc_share_reads_resumed_runs_from_their_first_segment_and_weighs_the_matched_term(tmp_path: Path) -> None:
    resumed = tmp_path / "idam_LC"
    _metrics(resumed, "metrics.segment1.csv", [(9, 0.02, 40.0), (19, 0.01, 30.0)])  # before the resume
    weight_one = _metrics(resumed, "metrics.csv", [(29, 0.005, 10.0), (39, 0.004, 8.0)])
    matched = _metrics(tmp_path / "idam_LCm", "metrics.csv", [(9, 0.03, 50.0), (39, 0.002, 5.16)])
    rows = {"idam/LC": [{"metrics_csv": str(weight_one)}], "idam/LC-matched": [{"metrics_csv": str(matched)}]}
    assert lc_share_lines(rows) == [
        "## Size of the LC term during training",
        "",
        "- LC + IDAM, weight 1: LC term 0.02 at the first logged step, 0.004 at the last (weighted: 0.05 % of the "
        "total training loss 8)",
        "- LC + IDAM, weight 51.6: LC term 0.03 at the first logged step, 0.002 at the last (weighted: 2 % of the "
        "total training loss 5.16)",
    ]
    assert lc_share_lines({"idam/LC": [{"metrics_csv": str(tmp_path / "gone.csv")}]}) == []
