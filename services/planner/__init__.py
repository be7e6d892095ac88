"""Planner service: the Latent Space Roadmap and the graph searches that turn it into plans."""
