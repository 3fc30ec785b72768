"""User errors on the command line: one or two lines on stderr, exit code 2 (arguments, configs) or 1 (files).

Two cases run ``python -m lcreg.cli`` in a subprocess (what a user sees); the others call :func:`lcreg.cli.main` the
way the console script does (``sys.argv``, no arguments). ``LCREG_DEBUG=1`` brings the traceback back.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import lcreg
from lcreg.checkpoints import CheckpointNotFoundError
from lcreg.cli import main

from _cli_runs import CONFIGS  # type: ignore[import-not-found]

DVDS = str(CONFIGS / "dvds.yaml")
DVDS_DATA = str(CONFIGS / "data" / "embedded.yaml")
SRC = str(Path(lcreg.__file__).resolve().parents[1])

pytestmark = pytest.mark.usefixtures("isolated_cli")


def _lcreg(*args: str, cwd: Path, debug: bool = False) -> subprocess.CompletedProcess[str]:
    path = os.pathsep.join([SRC, os.environ.get("PYTHONPATH", "")])
    env = {**os.environ, "PYTHONPATH": path, "WANDB_MODE": "disabled"}
    env.pop("LCREG_DEBUG", None)
    env.pop("JSONARGPARSE_DEBUG", None)
    if debug:
        env["LCREG_DEBUG"] = "1"
    return subprocess.run(
        [sys.executable, "-m", "lcreg.cli", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=120
    )


@pytest.mark.parametrize(
    ("args", "code", "names"),
    [
        (["fit", "--config", DVDS, "--model.init_args.max_iterations", "abc"], 2, "--model.init_args.max_iterations"),
        (["test", "--config", DVDS, "--ckpt_path", "broken.ckpt"], 1, "broken.ckpt"),
        (["fit", "--config", DVDS, "--data.init_args.batch_size", "-4"], 2, "`batch_size` must be"),
        (["fit", "--config", DVDS, "--trainer.max_epochs", "abc"], 2, "expected int or None, got 'abc'"),
        (["test", "--config", DVDS, "--ckpt_path", "notes.txt"], 1, "notes.txt': not a torch.save file"),
        (["fit", "--config", DVDS, "--model.init_args.max_iterations", "-1"], 2, "DVDs: `max_iterations` must be"),
    ],
    ids=["bad-value", "bad-ckpt", "refused-data-value", "union-value", "text-as-ckpt", "refused-model-value"],
)
def test_a_user_error_is_two_lines_and_an_exit_code(tmp_path: Path, args: list[str], code: int, names: str) -> None:
    """Before: exit 2 with 60 lines (usage + report) or exit 1 with a 40-line traceback ending in an UnpicklingError."""
    (tmp_path / "broken.ckpt").write_bytes(b"\x80\x02not a checkpoint")
    (tmp_path / "notes.txt").write_text("hello notes")  # was "(KeyError: 101)"
    result = _lcreg(*args, cwd=tmp_path)
    assert result.returncode == code, result.stderr
    _assert_two_lines(result.stderr, names)
    assert result.stdout == ""


def _assert_two_lines(stderr: str, names: str) -> None:
    lines = [line for line in stderr.splitlines() if not line.startswith("Seed set to")]  # Lightning's info line
    assert len(lines) <= 2 and lines[0].startswith("lcreg: error: ") and names in lines[0], stderr
    assert "Traceback" not in stderr and "LCREG_DEBUG=1" in lines[-1]


@pytest.mark.parametrize(
    ("args", "code", "names"),
    [
        (["fit", "--config", "absent.yaml"], 2, "absent.yaml"),
        (["test", "--config", DVDS, "--weights", "no-such-weights"], 1, "no-such-weights"),
        (["fit", "--config", DVDS, "--ckpt_path", "last"], 1, "nothing to resume"),
        (["fit", "--config", str(CONFIGS / "models" / "icp.yaml"), "--config", DVDS_DATA], 2, "nothing to train"),
    ],
    ids=["missing-config", "unknown-weights", "nothing-to-resume", "nothing-to-train"],
)
def test_the_console_entry_point_reports_user_errors_in_two_lines(
    args: list[str], code: int, names: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Before: 51 lines (missing config) or a 31-line traceback ending in UnknownPretrainedError."""
    monkeypatch.setattr(sys, "argv", ["lcreg", *args])
    with pytest.raises(SystemExit) as exit_code:
        main()
    assert exit_code.value.code == code
    _assert_two_lines(capsys.readouterr().err, names)


def test_lcreg_debug_shows_the_traceback(tmp_path: Path) -> None:
    result = _lcreg("test", "--config", DVDS, "--ckpt_path", "absent.ckpt", cwd=tmp_path, debug=True)
    assert result.returncode == 1
    assert "Traceback" in result.stderr and "CheckpointNotFoundError" in result.stderr


def test_unexpected_exceptions_keep_their_traceback() -> None:
    """A bug is not a user error: `_exit_on` re-raises it (the interpreter prints its traceback)."""
    from lcreg.cli import _exit_on

    with pytest.raises(KeyError, match="bug"):
        _exit_on(KeyError("bug"))
    with pytest.raises(SystemExit) as exit_code:
        _exit_on(CheckpointNotFoundError("x.ckpt", "no such file"))
    assert exit_code.value.code == 1


def test_condense_parser_error_names_the_innermost_key() -> None:
    from lcreg.cli import condense_parser_error

    report = """Parser key "model":
  Does not validate against any of the Union subtypes
  Errors:
    - Problem with given class_path 'lcreg.models.dvds.DVDs':
        Parser key "max_iterations":
          Expected a <class 'int'>. Got value: abc
    - Expected a <class 'NoneType'>"""
    assert condense_parser_error(report) == "--model.init_args.max_iterations: Expected a <class 'int'>. Got value: abc"
    assert condense_parser_error("unrecognized arguments: --x\n  more") == "unrecognized arguments: --x more"
