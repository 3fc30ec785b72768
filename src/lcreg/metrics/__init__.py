"""Registration metrics: per-pair errors (``functional``) and their ``torchmetrics`` shells (``registration``)."""
