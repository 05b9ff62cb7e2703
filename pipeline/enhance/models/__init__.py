"""Networks of the enhancer: VAE, latent U-Net, ControlNet branch, residual regressor."""
