from __future__ import annotations

import threading

import pytest

from lcreg.reference import reference_active, reference_mode


def test_reference_mode_is_active_only_inside_the_block_and_nests() -> None:
    assert not reference_active()
    with reference_mode():
        assert reference_active()
        with reference_mode():
            assert reference_active()
        assert reference_active()
    assert not reference_active()


def test_reference_mode_is_left_on_an_exception() -> None:
    with pytest.raises(RuntimeError, match="boom"), reference_mode():
        raise RuntimeError("boom")
    assert not reference_active()


def test_reference_mode_is_local_to_the_thread() -> None:
    seen: list[bool] = []
    with reference_mode():
        worker = threading.Thread(target=lambda: seen.append(reference_active()))
        worker.start()
        worker.join()
    assert seen == [False]
