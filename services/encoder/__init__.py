"""Encoder service: the action-VAE that maps images to latents and latents back to images."""
