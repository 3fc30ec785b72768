"""How far a rigid motion moves a cloud off its own surface (point-to-plane), and the same for random motions.

A registration error is a rigid motion ``E`` of the source in its own frame (``E = T_gt^-1 T_pred``). Its
**surface residual** is the mean point-to-plane distance of the moved source points ``x`` to the object's surface,
sampled by points ``y`` with normals ``n_y``:

``r(E) = mean_x |n_y . (E x - y)|``,  ``y`` the surface point nearest to ``E x``.

A motion along a symmetry of the shape (a sphere turned about its centre, a plane slid within itself, a cylinder
turned about its axis) leaves ``r`` near 0 however large it is; a motion of the same size in a direction the surface
pins down moves it by about the motion's displacement. The ratio of ``r(E)`` to ``r`` of random motions of the same
rotation angle and translation length (:func:`random_motions_like`) therefore says whether an error lies along
directions the shape barely constrains (ratio well below 1) or is a plain misalignment (about 1). The ICP
literature's degeneracy analysis (Gelfand et al., "Geometrically stable sampling for the ICP algorithm", 3DIM 2003)
measures the same to first order, from the eigen-directions of the point-to-plane information matrix; this is the
finite-motion version, with no linearisation.
"""

from __future__ import annotations

import torch

from lcreg.checks import check_points, check_same_batch, check_shape, check_transform
from lcreg.geometry import se3, so3
from lcreg.geometry.neighbors import gather_points, knn_indices
from lcreg.geometry.precision import full_precision

__all__ = ["random_motions_like", "surface_residual"]


@full_precision
def surface_residual(
    points: torch.Tensor, motion: torch.Tensor, surface: torch.Tensor, normals: torch.Tensor
) -> torch.Tensor:
    """Mean point-to-plane distance of ``points`` moved by ``motion`` to a surface sampled by points with normals.

    Args:
        points: Clouds ``(B, K, 3)`` on the surface (e.g. a pair's clean source points).
        motion: Rigid motions ``(B, 4, 4)`` in the frame of ``points`` and ``surface``.
        surface: The surface's points ``(B, P, 3)`` (e.g. the whole object ``points`` come from).
        normals: Unit normals of ``surface`` ``(B, P, 3)``; their sign does not matter.

    Returns:
        ``(B,)`` residuals ``mean_k |n_y . (E x_k - y)|``, ``y`` the surface point nearest to ``E x_k``, in the units
        of the points, ``>= 0``; 0 for the identity when ``points`` are surface points. No autograd.

    Raises:
        ShapeError, TypeError, NonFiniteError: On invalid clouds, normals or motions.
    """
    check_points(points, "points")
    check_transform(motion, "motion")
    check_points(surface, "surface")
    check_points(normals, "normals")
    check_same_batch(points=points, motion=motion, surface=surface, normals=normals)
    check_shape(normals, tuple(surface.shape), "normals")
    with torch.no_grad():
        moved = se3.transform_points(motion, points)  # (B, K, 3)
        nearest = knn_indices(moved, surface, 1)[..., 0]  # (B, K)
        offset = moved - gather_points(surface, nearest)  # (B, K, 3)
        return (offset * gather_points(normals, nearest)).sum(-1).abs().mean(-1)


def random_motions_like(motion: torch.Tensor, draws: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """Random rigid motions with the rotation angle and translation length of each of ``motion``.

    Args:
        motion: Rigid motions ``(B, 4, 4)``.
        draws: Motions drawn per item, ``>= 1``.
        generator: Source of the uniformly random rotation axes and translation directions.

    Returns:
        ``(B, draws, 4, 4)``: item ``b``'s draws all turn by ``b``'s angle about a random axis and move by the length
        of ``b``'s translation in a random direction.

    Raises:
        ValueError: If ``draws < 1``.
        ShapeError, TypeError, NonFiniteError: On invalid motions.
    """
    check_transform(motion, "motion")
    if draws < 1:
        raise ValueError(f"`draws` must be >= 1, got {draws}")
    rot, trans = se3.split(motion)  # (B, 3, 3), (B, 3)
    angle = so3.log(rot).norm(dim=-1)  # (B,) radians
    length = trans.norm(dim=-1)  # (B,)
    shape = (motion.shape[0], draws, 3)
    axes = torch.randn(shape, generator=generator, dtype=motion.dtype).to(motion.device)
    directions = torch.randn(shape, generator=generator, dtype=motion.dtype).to(motion.device)
    axes = axes / axes.norm(dim=-1, keepdim=True)
    directions = directions / directions.norm(dim=-1, keepdim=True)
    rotations = so3.exp(axes * angle[:, None, None])  # (B, draws, 3, 3)
    return se3.make_transform(rotations, directions * length[:, None, None])
