"""``lcreg register`` end to end: one pair with every output, many pairs with scores and resume, exit codes."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from _register_pairs import errors  # type: ignore[import-not-found]
from lcreg.cli import main
from lcreg.data.io import read_points
from lcreg.registration.api import default_pipeline
from lcreg.registration.outputs import read_transform, write_ply

SMALL_CLOUDS = default_pipeline().small or default_pipeline().method


@pytest.fixture()
def files(tmp_path, pair):
    src, ref, gt = pair
    return write_ply(tmp_path / "src.ply", src), write_ply(tmp_path / "ref.ply", ref), gt


def _exit_code(args, capsys) -> tuple[int, str]:
    with pytest.raises(SystemExit) as info:
        main(["register", *args])
    return int(info.value.code), capsys.readouterr().err


def test_one_pair_prints_and_writes_everything(files, tmp_path, capsys):
    src, ref, gt = files
    out, aligned = tmp_path / "T.json", tmp_path / "aligned.ply"
    main(["register", str(src), str(ref), "--out", str(out), "--save-aligned", str(aligned)])
    text = capsys.readouterr().out
    assert "transform (maps source points into the reference frame)" in text and "fitness:" in text
    assert f"wrote {out}" in text and f"wrote {aligned}" in text and "ms" in text
    estimate = read_transform(out)
    assert errors(estimate, gt)[0] < 1.0
    moved = read_points(aligned)
    np.testing.assert_allclose(moved, read_points(src) @ estimate[:3, :3].T + estimate[:3, 3], atol=1e-4)
    assert json.loads(out.read_text())["method"] == SMALL_CLOUDS  # 3,000 points: the default's method for objects


def test_init_file_is_used(files, tmp_path, capsys):
    src, ref, gt = files
    init = tmp_path / "init.txt"
    np.savetxt(init, gt)
    out = tmp_path / "T.npy"
    main(["register", str(src), str(ref), "--method", "icp", "--init", str(init), "--out", str(out)])
    assert errors(np.load(out), gt)[0] < 0.5


def test_user_errors_exit_non_zero_and_write_nothing(files, tmp_path, capsys):
    src, ref, _ = files
    out = tmp_path / "T.txt"
    empty = tmp_path / "empty.ply"
    empty.write_bytes(b"")
    code, err = _exit_code([str(empty), str(ref), "--out", str(out)], capsys)
    assert code == 1 and "empty.ply" in err and len(err.strip().splitlines()) == 2
    code, err = _exit_code([str(tmp_path / "missing.pcd"), str(ref), "--out", str(out)], capsys)
    assert code == 1 and "missing.pcd" in err
    code, err = _exit_code([str(src), str(ref), "--method", "sift"], capsys)
    assert code == 2 and "unknown method 'sift'" in err
    code, err = _exit_code([str(src), str(ref), "--out", str(tmp_path / "T.csv")], capsys)
    assert code == 1 and "extension" in err
    code, err = _exit_code([str(src)], capsys)
    assert code == 2 and "SRC and REF" in err
    code, err = _exit_code([str(src), str(ref), "--method", "dcp"], capsys)  # learned, no shipped weights
    assert code == 2 and "'dcp' has no shipped weights" in err and "--weights" in err
    assert not out.exists()


def test_help_lists_methods_and_weights(capsys):
    with pytest.raises(SystemExit):
        main(["register", "--help"])
    text = capsys.readouterr().out
    for name in ("ransac+icp", "fgr", "icp", "dvds-modelnet40", "pointnetlk", "--plot", "--pairs", "--out"):
        assert name in text


def _pairs_csv(tmp_path, files, rows=3):
    src, ref, gt = files
    path = tmp_path / "pairs.csv"
    lines = ["src,ref,gt"] + [f"{src.name},{ref.name}," + " ".join(map(str, gt.reshape(-1)))] * rows
    path.write_text("\n".join(lines) + "\n")
    return path


def test_many_pairs_csv_scores_and_resumes(files, tmp_path, capsys):
    pairs = _pairs_csv(tmp_path, files)
    results = tmp_path / "res.csv"
    common = ["register", "--pairs", str(pairs), "--method", "fgr+icp", "--results", str(results), "--rte", "0.05"]
    main([*common, "--limit", "1", "--no-progress"])
    first = list(csv.DictReader(results.open()))
    assert len(first) == 1
    code, err = _exit_code(["--pairs", str(pairs), "--results", str(results)], capsys)
    assert code == 1 and "--resume" in err  # never overwrites earlier results
    main([*common, "--resume"])
    rows = list(csv.DictReader(results.open()))
    assert len(rows) == 3 and rows[0] == first[0]
    assert all(r["success"] == "1" and float(r["rre_deg"]) < 1.0 for r in rows)
    summary = json.loads(results.with_suffix(".summary.json").read_text())
    assert summary["overall"]["recall"] == 1.0 and summary["overall"]["pairs"] == 3
    assert summary["thresholds"] == {"rre_deg": 5.0, "rte": 0.05, "rmse": 0.2}
    code, err = _exit_code(["--pairs", str(pairs), "--method", "icp", "--results", str(results), "--resume"], capsys)
    assert code == 1 and "fgr+icp" in err  # resume refuses another method's file


def test_top_level_help_points_to_register(capsys):
    with pytest.raises(SystemExit):
        main(["--help"])
    assert "lcreg register SRC REF" in capsys.readouterr().out.replace("\n", " ")


def test_user_thresholds_keep_the_standard_recall(files, tmp_path):
    src, ref, gt = files
    pairs = tmp_path / "pairs.csv"
    moved = gt.copy()
    moved[:3, 3] += 0.03  # a ground truth 3 cm off: a miss at --rte 0.01, a hit at the CSV standard (no RTE limit)
    pairs.write_text(f"{src.name},{ref.name}," + " ".join(map(str, moved.reshape(-1))) + "\n")
    results = tmp_path / "res.csv"
    main(["register", "--pairs", str(pairs), "--method", "fgr+icp", "--results", str(results), "--rte", "0.01"])
    summary = json.loads(results.with_suffix(".summary.json").read_text())
    assert summary["overall"]["recall"] == 0.0 and summary["overall"]["recall_standard"] == 1.0
    assert summary["standard_thresholds"]["rte"] is None and summary["thresholds"]["rte"] == 0.01


def test_console_reports_dropped_nan_rows_in_one_line(tmp_path, pair):
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    src, ref, _ = pair
    src = src.copy()
    src[:7, 0] = np.nan
    np.save(tmp_path / "src.npy", src)
    np.save(tmp_path / "ref.npy", ref)
    lcreg = shutil.which("lcreg", path=str(Path(sys.executable).parent))
    assert lcreg is not None
    out = subprocess.run(
        [lcreg, "register", "src.npy", "ref.npy", "--method", "fgr+icp"], cwd=tmp_path, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    assert "lcreg register: warning: points_src (src.npy): dropped 7 of 3000 points with NaN/Inf" in out.stderr
    assert "(2993 points)" in out.stdout


def test_a_damaged_file_fails_its_pair_with_the_reason_and_the_run_goes_on(files, tmp_path, capsys):
    src, ref, gt = files
    (tmp_path / "damaged.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 9\n")
    (tmp_path / "empty.ply").write_bytes(b"")
    flat = " ".join(map(str, gt.reshape(-1)))
    lines = [f"{src.name},{ref.name},{flat}", f"damaged.ply,{ref.name},{flat}", f"{src.name},empty.ply,{flat}"]
    pairs = tmp_path / "pairs.csv"
    pairs.write_text("\n".join([*lines, f"{src.name},{ref.name},{flat}"]) + "\n")
    results = tmp_path / "res.csv"
    main(["register", "--pairs", str(pairs), "--method", "fgr+icp", "--results", str(results), "--no-progress"])
    rows = list(csv.DictReader(results.open()))
    assert [r["success"] for r in rows] == ["1", "0", "0", "1"]
    assert rows[0]["error"] == "" and "damaged.ply" in rows[1]["error"] and "empty.ply" in rows[2]["error"]
    assert rows[1]["method"] == "fgr+icp" and rows[1]["coarse_success"] == "0"
    summary = json.loads(results.with_suffix(".summary.json").read_text())
    assert summary["overall"]["recall"] == 0.5 and summary["overall"]["failed"] == 2
    assert summary["coarse"]["overall"]["pairs"] == 4
    assert "2 pairs could not be registered" in capsys.readouterr().out


def test_fallback_options_print_what_ran(files, capsys):
    src, ref, _gt = files
    main(["register", str(src), str(ref), "--method", "icp", "--fallback", "ransac+icp", "--min-fitness", "0.9"])
    text = capsys.readouterr().out
    assert "fallback:  icp fitness" in text and "ran ransac+icp" in text and "kept ransac+icp" in text


def test_the_default_pipeline_is_recorded_as_default(files, tmp_path):
    pairs, results = _pairs_csv(tmp_path, files, rows=1), tmp_path / "res.csv"
    main(["register", "--pairs", str(pairs), "--results", str(results), "--no-progress"])
    assert [r["method"] for r in csv.DictReader(results.open())] == ["default"]
    assert json.loads(results.with_suffix(".summary.json").read_text())["method"] == "default"
    main(["register", "--pairs", str(pairs), "--results", str(results), "--resume"])  # resumes its own method
