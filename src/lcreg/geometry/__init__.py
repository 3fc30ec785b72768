"""Pure, batched, device-agnostic torch geometry: SO(3)/SE(3), Euler angles, Procrustes, neighbours, Chamfer."""
