"""Pure, batched, device-agnostic torch geometry: SO(3)/SE(3), Euler angles, Procrustes, neighbours, Chamfer.

NaN/Inf policy. The element-wise batched maps (``so3.exp/log/hat/vee/quaternion_to_matrix``, the Euler
conversions, ``se3.exp/log/inverse/compose/transform_points/transform_normals``, ``neighbors.pairwise_sq_distances``
and ``cdist``) check dtype and shape only (free) and propagate NaN/Inf item by item: an item holding NaN/Inf gives a
non-finite result for that item and leaves the others exactly as they would be. They run inside loops (IC-LK
iterations, losses) where a finiteness check would cost a host synchronisation per call, so their callers validate at
the boundary: models' ``forward``, ``lcreg.register``, DataModules and file readers, metrics. Functions that take whole
clouds (``knn``, ``chamfer_distance``, ``weighted_kabsch``, ``estimate_normals``, ``surface.surface_residual``)
validate them once, with a typed error naming the argument (:mod:`lcreg.checks`).

Precision. Under autocast (mixed-precision training) every numerical function here computes in float32, whatever
autocast asks for (:mod:`lcreg.geometry.precision`).
"""
