"""Feature extractors that metrics are computed in.

* :mod:`mfm.evaluators.t2m`: the official T2M co-embedding evaluator of Guo et al. (published checkpoints, GloVe).
* :mod:`mfm.evaluators.contrastive`: the project's own motion-CLIP evaluator and action classifier.
"""

from mfm.evaluators.contrastive import (
    ActionClassifier,
    ContrastiveEvaluator,
    ContrastiveEvaluatorConfig,
    LoadedEvaluator,
    MotionEncoder,
    TextHead,
    duplicate_caption_mask,
    infonce_loss,
    load_evaluator,
    retrieval_accuracy,
    save_evaluator,
)
from mfm.evaluators.t2m import (
    POS_CLASSES,
    T2MEvaluator,
    T2MEvaluatorFilesMissing,
    WordVectorizer,
    resolve_t2m_files,
    t2m_dataset_for_skeleton,
)

__all__ = [
    "ActionClassifier",
    "ContrastiveEvaluator",
    "ContrastiveEvaluatorConfig",
    "LoadedEvaluator",
    "MotionEncoder",
    "POS_CLASSES",
    "T2MEvaluator",
    "T2MEvaluatorFilesMissing",
    "TextHead",
    "WordVectorizer",
    "duplicate_caption_mask",
    "infonce_loss",
    "load_evaluator",
    "resolve_t2m_files",
    "retrieval_accuracy",
    "save_evaluator",
    "t2m_dataset_for_skeleton",
]
