"""`train video`: the paper's shortcut LoRA on precomputed clips (config, data, base models, trainer, CLI)."""
