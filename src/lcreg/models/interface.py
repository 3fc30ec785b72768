"""The model interface every registration model offers: estimate a transform, validated, in any unit and dtype.

:class:`RegistrationInterface` is the inference half of :class:`~lcreg.models.base.RegistrationModule`: ``forward``
(what a host implements), ``register`` (validated inference in eval mode at ``unit_scale``), ``estimate``
(``forward`` then the ``refiner``), ``refine`` (local methods), the input checks and the dtype hooks. Training lives in
:mod:`lcreg.models.training`, evaluation in :mod:`lcreg.models.evaluation`; the constructor that wires all three is
:class:`~lcreg.models.base.RegistrationModule`'s.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any, ClassVar

import torch
from lightning.pytorch import LightningModule

from lcreg.checks import check_extent, check_points, check_same_batch, check_shape
from lcreg.nn.dtypes import check_compute_dtype, module_dtype, to_module_dtype
from lcreg.types import RegistrationBatch, RegistrationResult

__all__ = ["RegistrationInterface"]


class RegistrationInterface(LightningModule):
    """Inference: ``forward`` / ``register`` / ``estimate`` / ``refine`` and the checks of their inputs.

    Inputs: ``forward`` and ``register`` validate both clouds first (:meth:`validate_inputs`, a forward pre-hook
    installed by :meth:`_install_dtype_hooks`: typed errors that name ``points_src`` or ``points_ref``, before any
    layer runs). They accept float32 and float64 clouds and compute in the model's dtype
    (:func:`lcreg.nn.dtypes.module_dtype`); a forward hook returns ``transform_ref_src`` in the caller's dtype.
    """

    _min_points: int = 3
    _refiner: RegistrationInterface | None = None
    _plain_components: ClassVar[tuple[str, ...]] = ("refiner",)
    """Components kept as plain attributes (not submodules: never trained nor saved), set through ``_set_<name>``."""

    def __setattr__(self, name: str, value: Any) -> None:
        """``model.refiner = ICP()`` (and the other plain components) goes through its check, like the constructor.

        ``nn.Module`` would file a module under ``_modules`` past the read-only property, silently ignored.
        """
        if name in type(self)._plain_components:
            getattr(self, f"_set_{name}")(value)
        else:
            super().__setattr__(name, value)

    def _set_refiner(self, refiner: Any) -> None:
        """Check and set the refiner (``None`` or a registration model able to refine, e.g. ICP).

        Raises:
            TypeError: Not a registration model.
        """
        if refiner is not None and not isinstance(refiner, RegistrationInterface):
            raise TypeError(
                f"`refiner` must be a RegistrationModule (e.g. lcreg.baselines.classical.ICP), got {type(refiner)}"
            )
        object.__setattr__(self, "_refiner", refiner)

    unit_scale: float | None = None
    _input_dtypes: list[torch.dtype]

    def _install_dtype_hooks(self) -> None:
        """The input-check and dtype hooks of ``forward`` (called once by the constructor)."""
        self._input_dtypes = []
        self.register_forward_pre_hook(_inputs_to_model_dtype, with_kwargs=True)
        self.register_forward_hook(_transform_to_input_dtype, always_call=True)

    def forward(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        """Estimate ``transform_ref_src`` for ``points_src (B, N, 3)`` and ``points_ref (B, M, 3)``."""
        raise NotImplementedError

    @property
    def min_points(self) -> int:
        """Smallest cloud accepted (training adds its loss terms' minimum)."""
        return self._min_points

    @min_points.setter
    def min_points(self, value: int) -> None:
        self._min_points = value

    @property
    def descriptor_dim(self) -> int:
        """Width ``K`` of :meth:`descriptor_encoder`'s features (``self.encoder.feature_dim`` by default)."""
        dim = getattr(getattr(self, "encoder", None), "feature_dim", None)
        if not isinstance(dim, int):
            raise TypeError(f"{type(self).__name__} does not expose a descriptor width (`encoder.feature_dim`)")
        return dim

    def descriptor_encoder(self) -> Callable[[torch.Tensor], torch.Tensor]:
        """The model's encoder ``psi``: ``(B, n, 3) -> (B, K)`` or ``(B, n, K)`` (``self.encoder`` by default).

        Raises:
            TypeError: If the model has no ``encoder`` (loss terms such as LC need one).
        """
        encoder = getattr(self, "encoder", None)
        if not callable(encoder):
            raise TypeError(f"{type(self).__name__} has no `encoder` for descriptor-based loss terms")
        return encoder

    @property
    def refiner(self) -> RegistrationInterface | None:  # set: model.refiner = ICP() (checked, __setattr__)
        """The refinement step run after ``forward`` outside training (``None``: none)."""
        return self._refiner

    @refiner.setter
    def refiner(self, refiner: RegistrationInterface | None) -> None:
        self._set_refiner(refiner)

    def estimate(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        """``forward``, then the refiner (if any) from its estimate.

        The refined result keeps the coarse estimate in ``aux["coarse_transform_ref_src"]`` and adds the refiner's
        iterations to ``num_iters``.
        """
        result = self(points_src, points_ref)
        if self._refiner is None:
            return result
        coarse = result.transform_ref_src.detach()
        refined = self._refiner.refine(points_src, points_ref, coarse)
        refined.aux = {**result.aux, **refined.aux, "coarse_transform_ref_src": coarse}
        refined.num_iters = refined.num_iters.to(result.num_iters.device) + result.num_iters
        return refined

    def ground_truth(self, batch: RegistrationBatch) -> torch.Tensor:
        """``batch.transform_ref_src`` for supervised losses; a clear error when the batch has none."""
        if batch.transform_ref_src is None:
            raise ValueError(
                f"{type(self).__name__} is trained with a ground-truth pose, but the batch has no `transform_ref_src`"
            )
        return batch.transform_ref_src

    def validate_inputs(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> None:
        """Raise a typed error (naming the argument) for bad clouds.

        Checks type, dtype, shape, size, NaN/Inf, one batch size, and clouds whose points all coincide
        (:class:`~lcreg.checks.DegenerateCloudError`: no motion to recover), and a model converted to half precision
        (:func:`~lcreg.nn.dtypes.check_compute_dtype`).
        """
        check_compute_dtype(self)
        check_points(points_src, "points_src", self.min_points)
        check_points(points_ref, "points_ref", self.min_points)
        check_same_batch(points_src=points_src, points_ref=points_ref)
        check_extent(points_src, "points_src")
        check_extent(points_ref, "points_ref")

    @torch.no_grad()
    def register(self, points_src: torch.Tensor, points_ref: torch.Tensor) -> RegistrationResult:
        """Validated inference in eval mode (restores the previous mode), at ``unit_scale`` when it is set.

        Raises:
            TypeError, ShapeError, NonFiniteError, TooFewPointsError: Bad clouds (the message names the argument).
        """
        self.validate_inputs(points_src, points_ref)
        factor = None
        if self.unit_scale is not None:
            centred = points_ref - points_ref.mean(dim=1, keepdim=True)
            factor = self.unit_scale / centred.norm(dim=-1).amax(dim=1)  # (B,)
            points_src, points_ref = points_src * factor[:, None, None], points_ref * factor[:, None, None]
        was_training = self.training
        self.eval()
        try:
            result = self.estimate(points_src, points_ref)
        finally:
            self.train(was_training)
        if factor is not None:  # p_ref = R p_src + t holds at any scale k with t' = k t
            transform = result.transform_ref_src.clone()
            transform[:, :3, 3] /= factor[:, None].to(transform.dtype)
            result.transform_ref_src = transform
        return result

    def refine(self, points_src: torch.Tensor, points_ref: torch.Tensor, init: torch.Tensor) -> RegistrationResult:
        """Improve the estimates ``init (B, 4, 4)``; only local methods (ICP) implement it.

        Raises:
            TypeError: For a model that cannot start from an initial estimate.
        """
        raise TypeError(f"{type(self).__name__} cannot refine an initial estimate; use a local method such as ICP")

    def _model_batch(self, batch: RegistrationBatch) -> RegistrationBatch:
        """``batch`` validated and cast to the model's dtype (float64 data, float32 model, or the reverse).

        Raises:
            lcreg.checks.ShapeError: Normals not shaped as their cloud, a pose not ``(B, 4, 4)``, indices not ``(B,)``
                (named ``batch.<field>``).
        """
        self.validate_inputs(batch.points_src, batch.points_ref)
        b, n, m = batch.points_src.shape[0], batch.points_src.shape[1], batch.points_ref.shape[1]
        expected: dict[str, tuple[int, ...]] = {
            "normals_src": (b, n, 3),
            "normals_ref": (b, m, 3),
            "transform_ref_src": (b, 4, 4),
            "index": (b,),
        }
        for name, shape in expected.items():
            value = getattr(batch, name)
            if value is not None:
                check_shape(value, shape, f"batch.{name}")
        return replace(batch, **to_module_dtype(self, vars(batch)))


def _inputs_to_model_dtype(
    module: RegistrationInterface, args: tuple[Any, ...], kwargs: dict[str, Any]
) -> tuple[tuple[Any, ...], dict[str, Any]]:
    """Forward pre-hook: validates the two clouds (errors name them), casts them to the model's dtype.

    Remembers the caller's dtype for :func:`_transform_to_input_dtype`.
    """
    if args and isinstance(args[0], RegistrationBatch):  # Lightning's DDP redirects training_step through forward
        module._input_dtypes.append(module_dtype(module) or torch.float32)
        return args, kwargs
    clouds = [*args[:2], *(kwargs[k] for k in ("points_src", "points_ref") if k in kwargs)]
    if len(clouds) == 2:
        module.validate_inputs(*clouds)
    first = next((a for a in (*args, *kwargs.values()) if isinstance(a, torch.Tensor) and a.is_floating_point()), None)
    module._input_dtypes.append(first.dtype if first is not None else module_dtype(module) or torch.float32)
    return to_module_dtype(module, args), to_module_dtype(module, kwargs)


def _transform_to_input_dtype(module: RegistrationInterface, args: Any, output: Any) -> Any:
    """Forward hook: ``transform_ref_src`` back in the caller's dtype (float64 in, float64 out)."""
    dtype = module._input_dtypes.pop() if module._input_dtypes else None
    if isinstance(output, RegistrationResult) and dtype is not None and output.transform_ref_src.dtype != dtype:
        output.transform_ref_src = output.transform_ref_src.to(dtype)
    return output
