"""APN service: the Action Proposal Network that names the action between two latent states."""
