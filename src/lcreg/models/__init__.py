"""LightningModules: the shared :class:`~lcreg.models.base.RegistrationModule` and DVDs."""
