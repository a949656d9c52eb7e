"""Training: the LightningModule, its losses, the runner, callbacks, checkpoints."""
