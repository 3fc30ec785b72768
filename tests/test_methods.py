"""lcreg.methods: the one table of methods, and every other table derived from it."""

from __future__ import annotations

import importlib

import pytest

import lcreg
from lcreg.config import configs_root
from lcreg.methods import METHODS, class_names, learned_methods, method_of_class, pretrained_weights
from lcreg.models.base import RegistrationModule
from lcreg.registration.methods import CLASSICAL, LEARNED, available_methods
from lcreg.weights import REGISTRY


@pytest.mark.parametrize("name", list(METHODS))
def test_each_method_names_an_lcreg_class_and_its_config_builds_it(name: str) -> None:
    import yaml

    info = METHODS[name]
    cls = getattr(importlib.import_module(info.module), info.class_name)
    assert issubclass(cls, RegistrationModule) and getattr(lcreg, info.class_name) is cls
    config = yaml.safe_load((configs_root() / info.config).read_text())
    assert config["model"]["class_path"] == info.class_path
    assert method_of_class(info.class_path) is info
    assert info.learned == ("optimizer" in config["model"]["init_args"])  # classical methods train nothing


def test_register_pretrained_and_lazy_names_are_read_from_the_table() -> None:
    assert list(LEARNED) == learned_methods() and {**LEARNED, **CLASSICAL}.keys() == METHODS.keys()
    assert all(LEARNED[n] == METHODS[n].class_path for n in LEARNED)
    assert set(available_methods()) >= set(METHODS)
    assert {n: s.class_path for n, s in REGISTRY.items()} == {
        n: m.class_path for n, (m, _) in pretrained_weights().items()
    }
    assert all(name in lcreg.__all__ for name in class_names()) and method_of_class("x.Y") is None
