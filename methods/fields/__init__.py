"""Language fields on Gaussians: feature autoencoders, the time-agnostic relevance query, and the
time-varying fields (status deformable network, Non-Status baseline)."""
