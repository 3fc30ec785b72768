"""The README's first command, as written there, on the real fragments: the transform, the file and the picture."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from lcreg.data.pairlists import read_pair_list
from lcreg.metrics.functional import rotation_error_deg, translation_error

from _shared_data import REPO_ROOT, SHARED_DATA, shared_data  # type: ignore[import-not-found]

pytestmark = pytest.mark.data


def _quickstart_command() -> list[str]:
    text = (REPO_ROOT / "README.md").read_text()
    section = text.split("## Register two scans", 1)[1]
    block = re.search(r"```bash\n(.*?)```", section, re.S)
    assert block is not None
    return block.group(1).replace("\\\n", " ").split()


def test_readme_quickstart_registers_two_fragments_and_draws_them(tmp_path):
    shared_data("3dmatch")
    command = _quickstart_command()
    assert command[:2] == ["lcreg", "register"] and "--plot" in command
    command = [a.replace("../shared/data", str(SHARED_DATA)) for a in command]
    lcreg = shutil.which("lcreg", path=str(Path(sys.executable).parent))
    assert lcreg is not None
    out = subprocess.run([lcreg, *command[1:]], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "transform (maps source points into the reference frame)" in out.stdout
    estimate = np.loadtxt(tmp_path / command[command.index("--out") + 1])
    scene = SHARED_DATA / "3dmatch" / "benchmarks" / "3DMatch" / "7-scenes-redkitchen"
    gt = next(p for p in read_pair_list(scene) if p.name.endswith("/24-35")).transform_ref_src
    pred, truth = torch.tensor(estimate)[None], torch.tensor(gt)[None]
    assert float(rotation_error_deg(pred, truth)[0]) < 2.0 and float(translation_error(pred, truth)[0]) < 0.1
    from matplotlib.image import imread

    image = imread(tmp_path / command[command.index("--plot") + 1])[..., :3]
    orange = np.abs(image - np.array([0xE6, 0x55, 0x0D]) / 255).sum(-1) < 0.15
    blue = np.abs(image - np.array([0x31, 0x82, 0xBD]) / 255).sum(-1) < 0.15
    assert orange.sum() > 2000 and blue.sum() > 2000  # both clouds drawn: not a blank picture
