"""Shared pieces of the tests that drive the ``lcreg`` CLI: config paths, YAML loading and a tiny-run budget.

Tests that call the CLI also request the ``isolated_cli`` fixture (``tests/conftest.py``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from lcreg.cli import main

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
TINY_RUN = [
    "--trainer.fast_dev_run=true",
    "--trainer.enable_progress_bar=false",
    "--trainer.enable_model_summary=false",
    "--data.init_args.num_points=96",
    "--data.init_args.batch_size=2",
]
SYNTHETIC = ["--data.init_args.num_train=2", "--data.init_args.num_val=2", "--data.init_args.num_test=2"]


def load_yaml(path: Path) -> dict[str, Any]:
    """A config file as a dict."""
    return yaml.safe_load(path.read_text())


def fit_then_test_embedded(name: str) -> None:
    """``lcreg fit`` then ``lcreg test`` on ``configs/embedded/<name>.yaml`` with the tiny budget."""
    config = str(CONFIGS / "embedded" / f"{name}.yaml")
    main(["fit", "--config", config, *TINY_RUN, *SYNTHETIC])
    main(["test", "--config", config, *TINY_RUN, *SYNTHETIC])
