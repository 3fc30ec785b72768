"""``lcreg fit|test --trainer.precision bf16-mixed``: mixed-precision training end to end (CPU autocast here; the same
path runs on a GPU), with float32 weights, checkpoints and metrics."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest
import torch

from lcreg.cli import main

from _cli_runs import SYNTHETIC, TINY_DVDS, TINY_RUN, config_args, host_composition

BF16 = "--trainer.precision=bf16-mixed"


def _logged(run: Path, prefix: str) -> dict[str, float]:
    rows = list(csv.DictReader((run / "metrics.csv").open()))
    return {k: float(v) for row in rows for k, v in row.items() if k.startswith(prefix) and v}


@pytest.mark.usefixtures("isolated_cli")
def test_dcp_fits_and_tests_in_bf16_mixed_with_finite_per_pair_errors(tmp_path: Path) -> None:
    config = host_composition("dcp", data="embedded")
    main(["fit", *config, *TINY_RUN, *SYNTHETIC, BF16])
    main(["test", *config, *TINY_RUN, *SYNTHETIC, BF16])
    rows = list(csv.DictReader((tmp_path / "test_per_pair.csv").open()))  # fast_dev_run: no logger, the cwd
    errors = [float(row["rotation_error_deg"]) for row in rows] + [float(row["translation_error"]) for row in rows]
    assert len(rows) == 2 and all(math.isfinite(e) and e >= 0.0 for e in errors)


@pytest.mark.usefixtures("isolated_cli")
def test_the_main_job_trains_in_bf16_mixed_and_saves_float32_weights(tmp_path: Path) -> None:
    save = [f"--trainer.logger.init_args.save_dir={tmp_path / 'runs'}"]
    main(["fit", *config_args("dvds.yaml"), *TINY_DVDS, BF16, *save])
    run = tmp_path / "runs" / "lcreg" / "version_0"
    logged = _logged(run, "val/")
    assert logged["val/rre_mean_deg"] >= 0.0 and all(math.isfinite(v) for v in logged.values())
    state = torch.load(run / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)["state_dict"]
    assert {t.dtype for t in state.values() if t.is_floating_point()} == {torch.float32}


@pytest.mark.usefixtures("isolated_cli")
def test_bf16_true_stops_at_the_first_batch_with_a_typed_error_that_names_bf16_mixed() -> None:
    """``bf16-true`` converts the weights and the batches to bfloat16: refused before any geometry runs in it."""
    config = host_composition("dcp", data="embedded")
    with pytest.raises(TypeError, match=r"DCP has torch.bfloat16 parameters.*bf16-mixed"):
        main(["fit", *config, *TINY_RUN, *SYNTHETIC, "--trainer.precision=bf16-true"])
