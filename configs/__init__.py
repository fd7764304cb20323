"""Presets (YAML): training (default, tiny, synthetic, humanml3d, humanml3d_mfm, kit), evaluation protocols
(eval_fast, eval_full) and accelerate launcher configs (accelerate/). A package only so that a non-editable install
carries them beside ``pipeline`` (``pipeline.config.CONFIG_DIR``); there is no code here."""
