"""The two generative systems: MoDi (``models.modi``) and GANimator (``models.ganimator``)."""
