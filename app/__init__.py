"""VLP service: indoor multi-target visible-light positioning."""
