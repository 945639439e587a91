"""SDM-UniPS networks: configuration presets, model, checkpoints, training."""
