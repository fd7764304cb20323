"""The training job: everything that makes a checkpoint.

Owns the trainer (``trainer``: the step, EMA, non-finite skipping, SIGTERM, one versioned state dict), fp16 loss
scaling (``loss_scaling``), validation loss (``validation``), metrics.jsonl / W&B / TensorBoard / loss.png
(``reporting``), the run folder's layout (``run_folder``) and checkpoints converted from published MFM/MDM weights
(``convert``). May import the shared modules, pipeline.data and mfm; nothing in generation or evaluation imports it.
"""
