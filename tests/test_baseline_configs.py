"""The LC + X hosts' compositions: the table's data protocol, LC on each host's encoder, `lcreg fit` end to end."""

from __future__ import annotations

from importlib import import_module
from pathlib import Path

import pytest
import torch

from lcreg.cli import build_cli, main
from lcreg.data.datamodule import ModelNet40DataModule
from lcreg.models.loss_terms import LocalConsistencyLoss
from lcreg.nn.local_consistency import LocalConsistency

from _cli_runs import CONFIGS, DCP_FAMILY, TINY_RUN, fit_then_test_embedded, host_composition  # type: ignore[import-not-found]
from _shared_data import shared_data

HOSTS = list(DCP_FAMILY)
CLASSES = {"dcp": "DCP", "prnet": "PRNet", "idam": "IDAM", "deepgmr": "DeepGMR"}


pytestmark = pytest.mark.usefixtures("isolated_cli")


@pytest.mark.parametrize("lc", [False, True], ids=["X", "LC+X"])
@pytest.mark.parametrize("host", HOSTS)
def test_modelnet_compositions_follow_the_table_protocol(host: str, lc: bool) -> None:
    cli = build_cli(host_composition(host, lc=lc, data="modelnet40"), run=False)
    data = cli.datamodule
    assert isinstance(data, ModelNet40DataModule)
    assert (data.protocol, data.root) == ("unseen_objects", "../shared/data/modelnet40_mini")
    protocol = data.pair_protocol
    assert (protocol.independent_sampling, protocol.noise_sigma, protocol.noise_clip) == (False, 0.01, 0.05)
    assert (protocol.num_points, protocol.max_angle_deg, protocol.max_translation) == (1024, 45.0, 0.5)
    monitors = [getattr(c, "monitor", "(last.ckpt)") for c in cli.trainer.checkpoint_callbacks]
    assert monitors == ["val/rre_mean_deg", "(last.ckpt)"]  # the best never on the test split; then last.ckpt
    assert [type(t) for t in cli.model.loss_terms] == ([LocalConsistencyLoss] if lc else [])


@pytest.mark.parametrize("host", HOSTS)
def test_lc_width_matches_the_host_encoder(host: str) -> None:
    cli = build_cli(host_composition(host, lc=True, data="modelnet40"), run=False)
    model = cli.model.eval()
    with torch.no_grad():
        features = model.descriptor_encoder()(torch.randn(2, 64, 3))
    (term,) = model.loss_terms
    assert features.shape[-1] == model.descriptor_dim == term.local_consistency.feature_dim


@pytest.mark.parametrize("host", HOSTS)
def test_fit_embedded_lc_composition_end_to_end(host: str) -> None:
    fit_then_test_embedded(host, lc=True)


@pytest.mark.data
def test_fit_dcp_lc_on_modelnet40(tmp_path: Path) -> None:
    root = shared_data("modelnet40_mini")
    main(["fit", "--config", str(CONFIGS / "dcp_lc.yaml"), *TINY_RUN, f"--data.init_args.root={root}"])


@pytest.mark.parametrize("host", HOSTS)
def test_every_host_rejects_an_lc_module_of_the_wrong_width(host: str) -> None:
    model_cls = getattr(import_module(f"lcreg.baselines.{host}"), CLASSES[host])
    width = model_cls().descriptor_dim
    wrong = LocalConsistencyLoss(LocalConsistency(feature_dim=7, num_local_points=64))
    with pytest.raises(ValueError, match=rf"built for 7 features, the encoder has {width}"):
        model_cls(loss_terms=[wrong])


def documented_fit_command(host: str) -> list[str]:
    """The ``lcreg fit`` arguments in the header comment of ``configs/models/<host>.yaml`` (``\\`` continuations
    joined, ``configs/...`` paths made absolute)."""
    header = [line.removeprefix("#").strip() for line in (CONFIGS / "models" / f"{host}.yaml").read_text().splitlines()]
    start = next(i for i, line in enumerate(header) if line.startswith("lcreg fit "))
    command = header[start]
    while command.endswith("\\"):
        start += 1
        command = f"{command[:-1]} {header[start]}"
    args = command.split()[2:]
    return [str(CONFIGS.parent / arg) if arg.startswith("configs/") else arg for arg in args]


@pytest.mark.parametrize("host", ["dcp", "prnet", "idam", "deepgmr"])
def test_documented_command_of_a_dcp_family_host_trains_on_its_pairs(host: str) -> None:
    # Regression (issue 23): the headers' commands omitted data/dcp_protocol.yaml, so a user copying them trained on two
    # independent clean samplings (the DVDs protocol), not on the same-points pairs with noise these hosts train on.
    cli = build_cli(documented_fit_command(host), run=False)
    assert type(cli.model).__name__.lower().startswith(host.removesuffix("v2"))
    protocol = cli.datamodule.pair_protocol
    assert (protocol.independent_sampling, protocol.noise_sigma, protocol.noise_clip) == (False, 0.01, 0.05)
