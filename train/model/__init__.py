"""train.model: the networks of DiT-Gaze — the two-stream Gaussian model and its fields, the DiT and U-Net
renderers, the diffusion, the latent codecs, and the RGB initialization of the Gaussians."""
