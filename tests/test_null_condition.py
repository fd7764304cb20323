"""FLAME's null condition in training: the dataset's own text encoder applied to the empty caption, stored in the
model and carried by every checkpoint, so sampling's unconditional half sees exactly what training dropped to."""

from __future__ import annotations

import numpy as np
import torch
from eval_worker import build_synthetic_dataset, train_tiny_model

from mfm.text import build_text_encoder
from pipeline.generation.inference import load_trained_model


def test_training_stores_the_empty_caption_encoding_and_the_checkpoint_carries_it(tmp_path_factory, tmp_path):
    manifest = build_synthetic_dataset(tmp_path_factory.getbasetemp() / "eval-synthetic")
    run = train_tiny_model(manifest, tmp_path / "run", "model.null_condition=empty_caption",
                           "model.cond_drop_prob=0.25", steps=1)
    trained = load_trained_model(run)
    assert trained.model_config.null_condition == "empty_caption"
    expected = build_text_encoder("minilm").encode([""]).pooled[0]  # the synthetic set's captions are MiniLM's
    np.testing.assert_allclose(trained.model.null_text.numpy(), expected, rtol=0, atol=1e-6)
    assert float(np.linalg.norm(expected)) > 0.5  # not the zero vector MDM's rule would give
    # The unconditional half of guidance is the model on that encoding.
    x, t = torch.randn(1, 8, trained.model_config.feature_dim), torch.tensor([0.3])
    cond = torch.randn(1, trained.model_config.cond_dim)
    with torch.no_grad():
        dropped = trained.model(x, t, cond, cond_mask=torch.tensor([True]))
        on_empty = trained.model(x, t, torch.from_numpy(expected)[None])
    torch.testing.assert_close(dropped, on_empty)
