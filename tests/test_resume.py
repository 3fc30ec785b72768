"""``lcreg.resume``: the metrics file of a run resumed where it had nothing left to train."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
from lightning.pytorch.loggers import CSVLogger

from lcreg.resume import keep_previous_metrics, restore_unlogged_metrics

EARLIER = "epoch,step,val/rre_median_deg\n0,49,3.5\n0,99,2.5\n"


class TeamLogger(CSVLogger):
    """A user's own CSV logger: a subclass, as teams write to add a field or a file name."""


class OtherLogger:
    """A logger that is not a CSV one (e.g. TensorBoard): its ``experiment`` has nothing to learn."""

    experiment = object()


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="", encoding="utf-8") as file:
        return list(csv.DictReader(file))


@pytest.mark.filterwarnings("ignore:Experiment logs directory")  # the folder of a resumed run, as in use
def test_a_csv_logger_subclass_appends_its_test_figures_to_the_metrics_file_put_back(tmp_path: Path) -> None:
    logger = TeamLogger(tmp_path, name="run", version=0)
    log_dir = Path(logger.log_dir)
    log_dir.mkdir(parents=True)
    (log_dir / "metrics.csv").write_text(EARLIER, encoding="utf-8")
    kept = keep_previous_metrics(log_dir)  # before the resumed run's writer starts (it clears the folder's file)
    assert logger.experiment is not None  # the resumed run starts at its cap and logs nothing, then tests
    restore_unlogged_metrics(kept, [OtherLogger(), logger])
    logger.log_metrics({"test/rre_median_deg": 2.25}, step=100)
    logger.save()  # a column the file lacks: the writer rewrites the file with every column
    rows = _rows(log_dir / "metrics.csv")
    assert [row["val/rre_median_deg"] for row in rows] == ["3.5", "2.5", ""]
    assert rows[-1]["test/rre_median_deg"] == "2.25"
    assert not list(log_dir.glob("metrics.segment*.csv"))
