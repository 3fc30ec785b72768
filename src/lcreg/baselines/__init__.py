"""Baselines behind the :class:`~lcreg.models.base.RegistrationModule` interface (one file per method)."""
