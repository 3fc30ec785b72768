from __future__ import annotations

import json
import subprocess
import sys

HEAVY = ("lightning", "pytorch_lightning", "lightning_fabric", "open3d", "wandb")

SCRIPT = f"""
import json, sys
import lcreg
from lcreg import LocalConsistency
assert LocalConsistency.__module__ == "lcreg.nn.local_consistency"
loaded = sorted(m for m in sys.modules if m.split(".")[0] in {HEAVY!r})
print(json.dumps({{"version": lcreg.__version__, "loaded": loaded}}))
"""


def test_light_import_does_not_load_lightning_open3d_or_wandb() -> None:
    proc = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert report["loaded"] == [], report["loaded"]
    assert report["version"]


def test_lazy_attributes_resolve_and_unknown_ones_raise() -> None:
    import lcreg

    assert "LocalConsistency" in dir(lcreg) and "DVDs" in dir(lcreg)
    assert lcreg.DVDs.__name__ == "DVDs"
    assert lcreg.RegistrationModule.__module__ == "lcreg.models.base"
    try:
        lcreg.NotAThing  # noqa: B018
    except AttributeError as err:
        assert "NotAThing" in str(err)
    else:  # pragma: no cover
        raise AssertionError("expected AttributeError")


def test_every_lazy_export_resolves_to_its_name() -> None:
    import lcreg

    for name in lcreg.__all__:
        if name != "__version__":
            assert getattr(lcreg, name).__name__ == name, name


def test_package_is_marked_typed() -> None:
    """PEP 561 marker next to the package (hatch's ``packages = ["src/lcreg"]`` puts it in the wheel)."""
    from pathlib import Path

    import lcreg

    assert (Path(lcreg.__file__).parent / "py.typed").is_file()
