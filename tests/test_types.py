from __future__ import annotations

import torch

from lcreg.geometry import se3
from lcreg.types import RegistrationResult


def test_fixed_iterations_result() -> None:
    transform = se3.identity(3, dtype=torch.float64)
    result = RegistrationResult.fixed_iterations(transform, num_iters=4, aux={"x": 1})
    assert result.transform_ref_src is transform
    assert result.converged.dtype == torch.bool and result.converged.tolist() == [True] * 3
    assert result.num_iters.dtype == torch.int64 and result.num_iters.tolist() == [4] * 3
    assert result.aux == {"x": 1} and result.residual_history is None
    assert RegistrationResult.fixed_iterations(transform).num_iters.tolist() == [1] * 3
    assert RegistrationResult.fixed_iterations(transform).aux == {}
