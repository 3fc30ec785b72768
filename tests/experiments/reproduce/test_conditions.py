"""``lcreg reproduce robustness`` and ``recall-curves``: smoke end to end, shared models, resume, the conditions."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

import lcreg.experiments.reproduce.conditions as conditions
import lcreg.experiments.reproduce.sweep
from _reproduce_outputs import assert_png_drawn, count_calls, read_jsonl  # type: ignore[import-not-found]
from lcreg.__main__ import main
from lcreg.experiments.benchmarking import METHODS
from lcreg.experiments.reproduce.budgets import DataChoice
from lcreg.experiments.reproduce.conditions import Condition, EvalRun, condition_batches, recall_of, run_conditions
from lcreg.experiments.reproduce.recall_curves import RECALL_CURVES, curve
from lcreg.experiments.reproduce.robustness import ROBUSTNESS

pytestmark = pytest.mark.usefixtures("isolated_cli")
pytest.importorskip("matplotlib")


def _expected_rows(experiment: Any, seeds: tuple[int, ...]) -> set[tuple[str, int | None, str]]:
    return {
        (m, s, c.key)
        for c in experiment.conditions
        for m in experiment.methods_of(c)
        for s in (seeds if METHODS[m].learned else (None,))
    }


def test_smoke_of_both_experiments_shares_the_trained_models_and_writes_every_row(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    fits = count_calls(monkeypatch, lcreg.experiments.reproduce.sweep, "fit")
    out = tmp_path / "out"
    main(["reproduce", "robustness", "--budget", "smoke", "--seeds", "0", "--out", str(out)])
    assert sorted(fits) == sorted(ROBUSTNESS.learned())  # every learned method trained once, classical never
    rows = read_jsonl(out / "robustness.jsonl")
    assert {(r["method"], r["seed"], r["condition"]) for r in rows} == _expected_rows(ROBUSTNESS, (0,))
    for r in rows:
        assert len(r["rre_deg"]) == len(r["rte"]) == r["pairs"] == 2
        assert (r["weights"] is None) == (not METHODS[r["method"]].learned)
    errors = {(r["method"], r["condition"]): r["rre_deg"] for r in rows}
    for name in ROBUSTNESS.methods:  # a 100 % crop keeps the clean pairs, and every method is deterministic
        assert errors[(name, "partial/1")] == errors[(name, "noise/0")], name
    text = (out / "robustness.md").read_text()
    assert "## Gaussian noise σ on both clouds: recall (RRE < 2°, RTE < 0.01), %" in text
    assert "| σ 0 | σ 0.01 |" in text and "| 100% kept | 90% kept |" in text
    assert "no numbers in the LaTeX" in text and "| DVDs, self-motion recipe |" in text
    assert_png_drawn(out / "robustness.png")

    main(["reproduce", "recall-curves", "--budget", "smoke", "--seeds", "0", "--out", str(out)])
    assert len(fits) == len(ROBUSTNESS.learned())  # recall-curves reused models.jsonl: nothing trained again
    rows = read_jsonl(out / "recall-curves.jsonl")
    assert {(r["method"], r["seed"], r["condition"]) for r in rows} == _expected_rows(RECALL_CURVES, (0,))
    text = (out / "recall-curves.md").read_text()
    assert "| RRE < 1° | RRE < 2° | RRE < 5° | RRE < 10° | median RRE ° |" in text
    assert "recall (RRE < 15°, RTE < 0.3 m)" in text and "recall (RRE < 5°, RTE < 2 m)" in text
    assert_png_drawn(out / "recall-curves.png")
    assert f"wrote {out / 'recall-curves.png'}" in capsys.readouterr().out


def test_a_rerun_evaluates_only_what_is_missing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    args = ["reproduce", "robustness", "--budget", "smoke", "--seeds", "0", "--only", "icp", "pointnetlk"]
    main([*args, "--out", str(tmp_path)])
    log = tmp_path / "robustness.jsonl"
    lines = log.read_text().splitlines()
    assert len(lines) == 2 * len(ROBUSTNESS.conditions)
    evaluated = count_calls(monkeypatch, conditions, "evaluate")
    fits = count_calls(monkeypatch, lcreg.experiments.reproduce.sweep, "fit")
    main([*args, "--out", str(tmp_path)])
    assert evaluated == [] and fits == []
    log.write_text("\n".join(lines[:-3]) + "\n")  # interrupted: the last three rows were not written
    main([*args, "--out", str(tmp_path)])
    assert len(evaluated) == 3 and fits == []
    again, before = read_jsonl(log)[-3:], [json.loads(x) for x in lines[-3:]]
    for row in (*again, *before):
        row.pop("ms_per_pair")
    assert again == before  # the same pairs and weights give the same per-pair errors


def test_a_method_whose_training_failed_is_reported_and_skipped(tmp_path: Path) -> None:
    from lcreg.models.base import NonFiniteTrainingError

    def diverging(*_: Any) -> dict[str, Any]:
        raise NonFiniteTrainingError("loss is NaN at step 1")

    experiment = ROBUSTNESS.select(["pcrnet"])
    experiment = replace(experiment, conditions=experiment.conditions[:2])
    run = EvalRun(experiment, "smoke", (0,), DataChoice(None), tmp_path)
    lines: list[str] = []
    log = run_conditions(run, progress=lines.append, train=diverging)
    assert log.rows == [] and any("no trained weights" in line for line in lines)
    assert "failed" in read_jsonl(tmp_path / "models.jsonl")[0]


def test_conditions_are_deterministic_and_apply_the_stated_noise_and_crop(tmp_path: Path) -> None:
    run = EvalRun(ROBUSTNESS, "smoke", (0,), DataChoice(None), tmp_path)
    budget = replace(run.budget, pairs=4)
    run = replace(run, experiment=replace(ROBUSTNESS, budgets={"smoke": budget}))
    clean = Condition("c", "noise", 0.0, "clean", options={"noise_sigma": 0.0, "noise_clip": 1.0})
    noisy = Condition("n", "noise", 0.03, "noisy", options={"noise_sigma": 0.03, "noise_clip": 1.0})
    crop = Condition("p", "partial", 0.5, "half", options={"partial": "viewpoint", "partial_keep": 0.5})
    a, b = condition_batches(run, clean), condition_batches(run, clean)
    assert all(torch.equal(x.points_src, y.points_src) for x, y in zip(a, b))  # the same pairs every time
    noise = torch.cat([n.points_ref - c.points_ref for n, c in zip(condition_batches(run, noisy), a)])
    assert noise.std().item() == pytest.approx(0.03, rel=0.1)  # the same pairs plus σ 0.03 noise
    gts = [c.transform_ref_src for c in a]
    assert all(torch.equal(x.transform_ref_src, g) for x, g in zip(condition_batches(run, noisy), gts))
    cropped = condition_batches(run, crop)
    assert {x.points_src.shape[1] for x in cropped} == {budget.points // 2}


def test_recall_and_curve_match_a_loop_over_pairs() -> None:
    rng = np.random.default_rng(0)
    rre, rte = rng.uniform(0, 8, 50), rng.uniform(0, 0.1, 50)
    rre[3] = np.nan
    row = {"rre_deg": rre.tolist(), "rte": rte.tolist()}
    loop = sum(1 for r, t in zip(rre, rte) if r < 2 and t < 0.01) / 50
    assert recall_of(row, 2.0, 0.01) == pytest.approx(loop)
    assert recall_of(row, 5.0, None) == pytest.approx(sum(1 for r in rre if r < 5) / 50)
    thresholds = np.array([0.0, 1.0, 4.5, 8.0])
    expected = [sum(1 for r in rre if r < t) / 50 for t in thresholds]  # NaN never counts
    assert curve(row, thresholds).tolist() == pytest.approx(expected)


def test_only_selects_methods_and_bad_patterns_are_one_line(tmp_path: Path, capsys) -> None:
    assert ROBUSTNESS.select(["icp", "dvds*"]).methods == ("dvds", "dvds_selfsup", "icp")
    with pytest.raises(SystemExit) as info:
        main(["reproduce", "recall-curves", "--budget", "smoke", "--only", "geotransformer", "--out", str(tmp_path)])
    assert info.value.code == 2
    assert "--only 'geotransformer' matches no method of recall-curves" in capsys.readouterr().err


def test_a_method_missing_seeds_is_labelled_with_how_many_were_evaluated(tmp_path: Path) -> None:
    from lcreg.experiments.reproduce.conditions import method_label

    run = EvalRun(ROBUSTNESS, "smoke", (0, 1), DataChoice(None), tmp_path)
    log = run.open_log()
    noise = ROBUSTNESS.conditions[0]
    for method, seed in (("dcp", 0), ("pointnetlk", 0), ("pointnetlk", 1), ("icp", None)):
        log.append({**run.key(method, seed, noise), "rre_deg": [1.0], "rte": [0.0], "pairs": 1})
    assert method_label(run, log, "dcp", [noise]) == "DCP-v2 (1 of 2 seeds)"
    assert method_label(run, log, "pointnetlk", [noise]) == "PointNetLK"
    assert method_label(run, log, "icp", [noise]) == "ICP point-to-point"  # classical: run once, not per seed
    assert method_label(run, log, "pointnetlk", ROBUSTNESS.conditions[:2]) == "PointNetLK (0 of 2 seeds)"
