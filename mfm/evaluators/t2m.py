"""The official text-to-motion evaluator of Guo et al. (EricGuo5513/text-to-motion, copied verbatim into MDM, MFM
and FlowMDM), rebuilt so that its published checkpoint loads strictly.

Published files (the user supplies them; nothing is downloaded here):

    {checkpoint_dir}/{t2m|kit}/text_mot_match/model/finest.tar    dict: movement_encoder, text_encoder,
                                                                   motion_encoder, epoch (+ optimiser states)
    {glove_dir}/our_vab_data.npy, our_vab_words.pkl, our_vab_idx.pkl   GloVe subset (300-D) and its vocabulary
    {t2m|kit}_mean.npy, {t2m|kit}_std.npy                          evaluator normalisation (MDM's ``dataset/``), or
    {checkpoint_dir}/{t2m|kit}/Comp_v6_KLD01|Comp_v6_KLD005/meta/{mean,std}.npy   (the T2M repository's layout)

Module attribute names (``main``, ``out_net``, ``input_emb``, ``pos_emb``, ``gru``, ``output_net``, ``hidden``)
are the reference's: they *are* the checkpoint's state-dict keys.

Differences from the reference wrapper (``EvaluatorModelWrapper.get_co_embeddings``), none of which changes an
embedding: the reference sorts a batch by motion length for ``pack_padded_sequence`` and returns the embeddings in
that sorted order (texts re-indexed to follow); here packing uses ``enforce_sorted=False`` and embeddings come back
**in input order**. Normalisation is done here (the reference's dataset does it), and each clip is placed in a
196-frame window zeroed (in normalised space) from its length on, which is how the reference's ground-truth loader
pads. The reference's loader also crops ground-truth clips to a multiple of 4 frames; that is the caller's choice.
Two reference behaviours are options, for the ``mdm`` evaluation protocol: ``keep_padding`` hands the encoder the
frames past each length as given (the reference's generated motions are sampled over the whole window), and caption
length rule 'padded' gives the text encoder 22 for every caption (the reference's generated-motion dataset).
"""

from __future__ import annotations

import logging
import pickle
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn.utils.rnn import pack_padded_sequence

log = logging.getLogger(__name__)

WORD_DIM = 300
"""GloVe vector size."""
MAX_TEXT_TOKENS = 20
"""Caption tokens kept before adding sos/eos (the reference's ``max_text_len``)."""
SENTENCE_SLOTS = MAX_TEXT_TOKENS + 2
COEMBEDDING_DIM = 512

POS_CLASSES: tuple[str, ...] = (
    "VERB", "NOUN", "DET", "ADP", "NUM", "AUX", "PRON", "ADJ", "ADV",
    "Loc_VIP", "Body_VIP", "Obj_VIP", "Act_VIP", "Desc_VIP", "OTHER",
)
"""The 15 POS one-hot classes, in the reference's index order (``POS_enumerator``)."""
POS_INDEX = {name: i for i, name in enumerate(POS_CLASSES)}

# "Very important" words whose class overrides the spaCy POS tag (utils/word_vectorizer.py), checked in this order.
# No word is in two lists; the reference lists 'dance' twice in Act, which a set ignores.
VIP_WORDS: dict[str, frozenset[str]] = {
    "Loc_VIP": frozenset({
        "left", "right", "clockwise", "counterclockwise", "anticlockwise", "forward", "back", "backward",
        "up", "down", "straight", "curve",
    }),
    "Body_VIP": frozenset({
        "arm", "chin", "foot", "feet", "face", "hand", "mouth", "leg", "waist", "eye", "knee", "shoulder", "thigh",
    }),
    "Obj_VIP": frozenset({
        "stair", "dumbbell", "chair", "window", "floor", "car", "ball", "handrail", "baseball", "basketball",
    }),
    "Act_VIP": frozenset({
        "walk", "run", "swing", "pick", "bring", "kick", "put", "squat", "throw", "hop", "dance", "jump", "turn",
        "stumble", "stop", "sit", "lift", "lower", "raise", "wash", "stand", "kneel", "stroll", "rub", "bend",
        "balance", "flap", "jog", "shuffle", "lean", "rotate", "spin", "spread", "climb",
    }),
    "Desc_VIP": frozenset({
        "slowly", "carefully", "fast", "careful", "slow", "quickly", "happy", "angry", "sad", "happily", "angrily",
        "sadly",
    }),
}

GLOVE_PREFIX = "our_vab"
SOURCES_HINT = (
    "These files are published with the official evaluator and are not part of this project: "
    "EricGuo5513/text-to-motion (README: download the pretrained 'checkpoints' and 'glove' archives), or "
    "GuyTevet/motion-diffusion-model (`bash prepare/download_t2m_evaluators.sh` -> t2m/ and kit/, "
    "`bash prepare/download_glove.sh` -> glove/; the normalisation is committed there as "
    "dataset/t2m_mean.npy, t2m_std.npy, kit_mean.npy, kit_std.npy)."
)


@dataclass(frozen=True)
class T2MDatasetSpec:
    """What the evaluator of one dataset expects."""

    name: str
    """'t2m' (HumanML3D) or 'kit' (KIT-ML): the checkpoint folder name."""
    feature_dim: int
    """Guo feature size, foot contacts included (the networks see ``feature_dim - 4``)."""
    comp_meta_folder: str
    """Folder of the T2M repository's copy of the evaluator normalisation (``{name}/{folder}/meta``)."""
    unit_length: int = 4
    """Temporal downsampling of the movement encoder; the GRU sees ``length // unit_length`` steps."""
    max_motion_length: int = 196
    """Longest clip the reference evaluates (frames)."""

    @property
    def movement_input_dim(self) -> int:
        return self.feature_dim - 4


T2M_DATASETS: dict[str, T2MDatasetSpec] = {
    "t2m": T2MDatasetSpec("t2m", 263, "Comp_v6_KLD01"),
    "kit": T2MDatasetSpec("kit", 251, "Comp_v6_KLD005"),
}
_SKELETON_TO_T2M = {"humanml3d": "t2m", "kit": "kit"}


def t2m_dataset_for_skeleton(skeleton: str) -> str:
    """The evaluator dataset name for a manifest skeleton name ('humanml3d' -> 't2m', 'kit' -> 'kit')."""
    try:
        return _SKELETON_TO_T2M[skeleton]
    except KeyError:
        raise ValueError(f"no official T2M evaluator for skeleton {skeleton!r} "
                         f"(only {sorted(_SKELETON_TO_T2M)})") from None


def _dataset_spec(dataset: str) -> T2MDatasetSpec:
    try:
        return T2M_DATASETS[dataset]
    except KeyError:
        raise ValueError(f"unknown T2M evaluator dataset {dataset!r}: expected one of {sorted(T2M_DATASETS)}") from None


# ----------------------------------------------------------------------------------------------------------------------
# Networks (networks/modules.py). Initialisation is PyTorch's default: these modules exist to load the checkpoint.


class MovementConvEncoder(nn.Module):
    """Two stride-2 convolutions (4x temporal downsampling) and a per-step Linear."""

    def __init__(self, input_size: int, hidden_size: int = 512, output_size: int = 512) -> None:
        super().__init__()
        # Indices 0 and 3 of `main` are the checkpoint's conv keys (main.0.*, main.3.*).
        self.main = nn.Sequential(
            nn.Conv1d(input_size, hidden_size, 4, 2, 1),
            nn.Dropout(0.2),
            nn.LeakyReLU(0.2),
            nn.Conv1d(hidden_size, output_size, 4, 2, 1),
            nn.Dropout(0.2),
            nn.LeakyReLU(0.2),
        )
        self.out_net = nn.Linear(output_size, output_size)

    def forward(self, inputs: torch.Tensor) -> torch.Tensor:
        """(B, T, input_size) -> (B, T // 4, output_size)."""
        return self.out_net(self.main(inputs.permute(0, 2, 1)).permute(0, 2, 1))


def _bigru_last_state(gru: nn.GRU, initial: nn.Parameter, inputs: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
    """Concatenated final forward/backward states (B, 2H) of a packed BiGRU, in input order."""
    hidden = initial.repeat(1, inputs.shape[0], 1)
    packed = pack_padded_sequence(inputs, lengths.cpu().long(), batch_first=True, enforce_sorted=False)
    _, last = gru(packed, hidden)  # (2, B, H), already permuted back to input order
    return torch.cat([last[0], last[1]], dim=-1)


def _output_net(in_size: int, hidden_size: int, output_size: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(in_size, hidden_size),
        nn.LayerNorm(hidden_size),
        nn.LeakyReLU(0.2),
        nn.Linear(hidden_size, output_size),
    )


class MotionEncoderBiGRUCo(nn.Module):
    """Linear -> BiGRU (learned initial state) -> MLP over the last states."""

    def __init__(self, input_size: int = 512, hidden_size: int = 1024, output_size: int = COEMBEDDING_DIM) -> None:
        super().__init__()
        self.input_emb = nn.Linear(input_size, hidden_size)
        self.gru = nn.GRU(hidden_size, hidden_size, batch_first=True, bidirectional=True)
        self.output_net = _output_net(hidden_size * 2, hidden_size, output_size)
        self.hidden = nn.Parameter(torch.randn(2, 1, hidden_size))

    def forward(self, inputs: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
        """inputs (B, T', input_size), lengths (B,) in downsampled steps -> (B, output_size)."""
        return self.output_net(_bigru_last_state(self.gru, self.hidden, self.input_emb(inputs), lengths))


class TextEncoderBiGRUCo(nn.Module):
    """(word vector + Linear(POS one-hot)) -> Linear -> BiGRU (learned initial state) -> MLP over the last states."""

    def __init__(self, word_size: int = WORD_DIM, pos_size: int = len(POS_CLASSES), hidden_size: int = 512,
                 output_size: int = COEMBEDDING_DIM) -> None:
        super().__init__()
        self.pos_emb = nn.Linear(pos_size, word_size)
        self.input_emb = nn.Linear(word_size, hidden_size)
        self.gru = nn.GRU(hidden_size, hidden_size, batch_first=True, bidirectional=True)
        self.output_net = _output_net(hidden_size * 2, hidden_size, output_size)
        self.hidden = nn.Parameter(torch.randn(2, 1, hidden_size))

    def forward(self, word_embs: torch.Tensor, pos_onehot: torch.Tensor, sent_lens: torch.Tensor) -> torch.Tensor:
        """word_embs (B, L, 300), pos_onehot (B, L, 15), sent_lens (B,) -> (B, output_size)."""
        inputs = self.input_emb(word_embs + self.pos_emb(pos_onehot))
        return self.output_net(_bigru_last_state(self.gru, self.hidden, inputs, sent_lens))


def build_t2m_networks(dataset: str = "t2m") -> dict[str, nn.Module]:
    """The three networks with the published sizes, keyed by their checkpoint entry names."""
    spec = _dataset_spec(dataset)
    return {
        "movement_encoder": MovementConvEncoder(spec.movement_input_dim, 512, 512),
        "text_encoder": TextEncoderBiGRUCo(WORD_DIM, len(POS_CLASSES), 512, COEMBEDDING_DIM),
        "motion_encoder": MotionEncoderBiGRUCo(512, 1024, COEMBEDDING_DIM),
    }


# ----------------------------------------------------------------------------------------------------------------------
# GloVe word vectorizer (utils/word_vectorizer.py)


def pos_class(word: str, pos: str) -> str:
    """The POS class of a known word: its VIP list if it is in one, else the tag if it is one of the 15, else OTHER."""
    for vip_class, words in VIP_WORDS.items():
        if word in words:
            return vip_class
    return pos if pos in POS_INDEX else "OTHER"


CAPTION_LENGTHS = ("sentence", "padded")
"""How long a caption is to the text encoder (its GRU stops there): 'sentence' = sos + tokens[:20] + eos, the
reference's ground-truth ``sent_len`` (``Text2MotionDatasetV2.__getitem__``); 'padded' = the 22 slots of the
unk-padded token list, what MDM's generated-motion dataset passed before MDM's fix of issue #182 (MFM's copy still
does: ``CompMDMGeneratedDataset``: ``cap_len = len(tokens)`` of the padded list re-split on '_')."""


def sentence_tokens(tokens: Sequence[str]) -> tuple[list[str], int]:
    """``sos/OTHER + tokens[:20] + eos/OTHER`` padded with ``unk/OTHER`` to 22 slots, and the unpadded length."""
    sentence = ["sos/OTHER", *tokens[:MAX_TEXT_TOKENS], "eos/OTHER"]
    sent_len = len(sentence)
    return sentence + ["unk/OTHER"] * (SENTENCE_SLOTS - sent_len), sent_len


def caption_length(tokens: Sequence[str], rule: str = "sentence") -> int:
    """The caption length the text encoder gets under ``rule`` (CAPTION_LENGTHS): 'sentence' counts sos + the
    first 20 tokens + eos (3 tokens -> 5); 'padded' is the length of the padded token list, always 22 (a reference
    token list re-split on '_' is 22 long unless a token holds '_', where the reference's vectorizer fails)."""
    if rule not in CAPTION_LENGTHS:
        raise ValueError(f"caption length rule must be one of {CAPTION_LENGTHS}, got {rule!r}")
    padded, sent_len = sentence_tokens(tokens)
    return len(padded) if rule == "padded" else sent_len


class _PlainUnpickler(pickle.Unpickler):
    """Builtins (list, dict, str, int) and numpy scalars only: a vocabulary file cannot run code."""

    _ALLOWED = {("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"), ("numpy", "dtype")}

    def find_class(self, module: str, name: str):
        if (module, name) in self._ALLOWED:
            return super().find_class(module, name)
        raise pickle.UnpicklingError(f"refusing to load {module}.{name}")


def _load_plain_pickle(path: Path, expected: type):
    try:
        with open(path, "rb") as f:
            value = _PlainUnpickler(f).load()
    except (pickle.UnpicklingError, EOFError, ValueError) as exc:
        raise ValueError(f"{path}: not a plain pickled {expected.__name__}: {exc}") from exc
    if not isinstance(value, expected):
        raise ValueError(f"{path}: expected a pickled {expected.__name__}, got {type(value).__name__}")
    return value


class WordVectorizer:
    """Maps ``word/POS`` tokens to (GloVe vector, 15-class POS one-hot); unknown words -> 'unk' vector + OTHER."""

    def __init__(self, vectors: np.ndarray, words: Sequence[str], word_to_row: dict[str, int], *,
                 source: str = "<memory>") -> None:
        vectors = np.asarray(vectors)
        if vectors.ndim != 2 or vectors.shape[1] != WORD_DIM:
            raise ValueError(f"{source}: word vectors must be (N, {WORD_DIM}), got {vectors.shape}")
        unindexed = [w for w in words if w not in word_to_row]
        if unindexed:
            raise ValueError(f"{source}: {len(unindexed)} listed word(s) have no index entry, e.g. {unindexed[:5]}")
        rows = np.array([word_to_row[w] for w in words], dtype=np.int64)
        if rows.size and (rows.min() < 0 or rows.max() >= len(vectors)):
            raise ValueError(f"{source}: vocabulary indexes rows outside the {len(vectors)} vectors")
        # As the reference: the known words are those listed in `words`, each at its `word_to_row` row.
        self.word_to_vec = {w: vectors[word_to_row[w]].astype(np.float32) for w in words}
        for required in ("sos", "eos", "unk"):
            if required not in self.word_to_vec:
                raise ValueError(f"{source}: vocabulary has no {required!r} entry")

    @classmethod
    def from_dir(cls, glove_dir: str | Path, prefix: str = GLOVE_PREFIX) -> WordVectorizer:
        glove_dir = Path(glove_dir)
        vectors = np.load(glove_dir / f"{prefix}_data.npy")  # allow_pickle stays False: a plain float array
        words = _load_plain_pickle(glove_dir / f"{prefix}_words.pkl", list)
        word_to_row = {str(w): int(i) for w, i in _load_plain_pickle(glove_dir / f"{prefix}_idx.pkl", dict).items()}
        return cls(vectors, words, word_to_row, source=str(glove_dir / prefix))

    def __len__(self) -> int:
        return len(self.word_to_vec)

    def lookup(self, token: str) -> tuple[np.ndarray, np.ndarray]:
        """One ``word/POS`` token -> (300-D float32 vector, 15-D float32 one-hot)."""
        word, sep, pos = token.rpartition("/")
        if not sep or not word:
            raise ValueError(f"token {token!r} is not 'word/POS' (HumanML3D/KIT caption files carry POS-tagged "
                             f"tokens; the shards keep them in meta.json captions[i].tokens)")
        onehot = np.zeros(len(POS_CLASSES), dtype=np.float32)
        if word in self.word_to_vec:
            onehot[POS_INDEX[pos_class(word, pos)]] = 1.0
            return self.word_to_vec[word], onehot
        onehot[POS_INDEX["OTHER"]] = 1.0
        return self.word_to_vec["unk"], onehot

    def encode_sentence(self, tokens: Sequence[str],
                        lengths: str = "sentence") -> tuple[np.ndarray, np.ndarray, int]:
        """Caption tokens -> word vectors (22, 300), POS one-hots (22, 15), caption length (:func:`caption_length`:
        sos/eos included; 'padded': 22)."""
        sentence, _ = sentence_tokens(tokens)
        vectors, onehots = zip(*(self.lookup(t) for t in sentence))
        return np.stack(vectors), np.stack(onehots), caption_length(tokens, lengths)

    def encode_batch(self, token_lists: Sequence[Sequence[str]],
                     lengths: str = "sentence") -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A batch of captions -> word_embs (B, 22, 300), pos_onehot (B, 22, 15), sent_lens (B,) int64 (``lengths``:
        a CAPTION_LENGTHS rule)."""
        if isinstance(token_lists, str) or any(isinstance(t, str) for t in token_lists):
            raise TypeError("token_lists must be a list of token lists (one list of 'word/POS' strings per caption)")
        if len(token_lists) == 0:
            raise ValueError("token_lists is empty")
        encoded = [self.encode_sentence(tokens, lengths) for tokens in token_lists]
        words = torch.from_numpy(np.stack([e[0] for e in encoded]))
        pos = torch.from_numpy(np.stack([e[1] for e in encoded]))
        lens = torch.tensor([e[2] for e in encoded], dtype=torch.int64)
        return words, pos, lens


# ----------------------------------------------------------------------------------------------------------------------
# Files and loading


class T2MEvaluatorFilesMissing(FileNotFoundError):
    """Some of the official evaluator's files are absent; ``missing`` lists them."""

    def __init__(self, missing: Sequence[Path], dataset: str, alternatives: Sequence[Path] = ()) -> None:
        self.missing = list(missing)
        lines = "\n".join(f"  - {p}" for p in self.missing)
        message = f"official T2M evaluator ({dataset}): {len(self.missing)} required file(s) missing:\n{lines}\n"
        if alternatives:
            message += "the normalisation may instead be at (or pass norm_dir=<folder with these names>):\n"
            message += "".join(f"  - {p}\n" for p in alternatives)
        super().__init__(message + SOURCES_HINT)


@dataclass(frozen=True)
class T2MEvaluatorFiles:
    checkpoint: Path
    glove_vectors: Path
    glove_words: Path
    glove_index: Path
    mean: Path
    std: Path


def _norm_candidates(spec: T2MDatasetSpec, checkpoint_dir: Path, norm_dir: Path | None) -> list[tuple[Path, Path]]:
    if norm_dir is not None:
        return [(norm_dir / f"{spec.name}_mean.npy", norm_dir / f"{spec.name}_std.npy")]
    meta = checkpoint_dir / spec.name / spec.comp_meta_folder / "meta"
    return [
        (checkpoint_dir / f"{spec.name}_mean.npy", checkpoint_dir / f"{spec.name}_std.npy"),
        (meta / "mean.npy", meta / "std.npy"),
    ]


def resolve_t2m_files(checkpoint_dir: str | Path, glove_dir: str | Path, dataset: str = "t2m",
                      norm_dir: str | Path | None = None) -> T2MEvaluatorFiles:
    """Paths of every file the evaluator needs; raises :class:`T2MEvaluatorFilesMissing` naming all absent ones.

    ``checkpoint_dir`` holds ``{dataset}/text_mot_match/model/finest.tar`` (the T2M ``checkpoints/`` folder, or
    MDM's repository root after ``prepare/download_t2m_evaluators.sh``). The normalisation is read from
    ``norm_dir/{dataset}_mean.npy`` when ``norm_dir`` is given, else from ``checkpoint_dir/{dataset}_mean.npy`` or
    the T2M layout ``checkpoint_dir/{dataset}/Comp_v6_KLD01|Comp_v6_KLD005/meta/mean.npy``.
    """
    spec = _dataset_spec(dataset)
    checkpoint_dir, glove_dir = Path(checkpoint_dir), Path(glove_dir)
    checkpoint = checkpoint_dir / spec.name / "text_mot_match" / "model" / "finest.tar"
    glove = [glove_dir / f"{GLOVE_PREFIX}{suffix}" for suffix in ("_data.npy", "_words.pkl", "_idx.pkl")]
    missing = [p for p in (checkpoint, *glove) if not p.is_file()]
    candidates = _norm_candidates(spec, checkpoint_dir, None if norm_dir is None else Path(norm_dir))
    norms = next(((m, s) for m, s in candidates if m.is_file() and s.is_file()), None)
    alternatives: list[Path] = []
    if norms is None:
        missing += [p for p in candidates[0] if not p.is_file()]
        alternatives = [p for pair in candidates[1:] for p in pair]
    if missing:
        raise T2MEvaluatorFilesMissing(missing, spec.name, alternatives)
    return T2MEvaluatorFiles(checkpoint, *glove, *norms)


def _load_checkpoint(path: Path, allow_pickle: bool) -> dict:
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=not allow_pickle)
    except Exception as exc:  # an unreadable or non-tensor pickle: say which file and how to proceed
        hint = "" if allow_pickle else (" (loaded with weights_only=True; if you trust this file, pass "
                                        "allow_pickle=True to load arbitrary pickled objects)")
        raise ValueError(f"{path}: cannot read the T2M evaluator checkpoint: {exc}{hint}") from exc
    if not isinstance(checkpoint, dict):
        raise ValueError(f"{path}: expected a dict checkpoint, got {type(checkpoint).__name__}")
    missing = [k for k in ("movement_encoder", "text_encoder", "motion_encoder") if k not in checkpoint]
    if missing:
        raise ValueError(f"{path}: not a text_mot_match checkpoint, missing entries {missing}")
    return checkpoint


def _load_norm(path: Path, spec: T2MDatasetSpec) -> np.ndarray:
    array = np.load(path).astype(np.float64)
    if array.shape != (spec.feature_dim,):
        raise ValueError(f"{path}: expected shape ({spec.feature_dim},) for the {spec.name} evaluator, "
                         f"got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{path}: contains NaN/inf")
    return array


class T2MEvaluator(nn.Module):
    """The official co-embedding evaluator: motions and POS-tagged captions -> 512-D embeddings, in input order.

    Build it with :meth:`from_files`. Inputs are *raw* (un-normalised) Guo features; the evaluator normalisation
    (``t2m_std`` already includes the /25 on the root and foot-contact groups) is applied here.
    """

    def __init__(self, dataset: str, vectorizer: WordVectorizer, mean: np.ndarray, std: np.ndarray) -> None:
        super().__init__()
        self.spec = _dataset_spec(dataset)
        networks = build_t2m_networks(dataset)
        self.movement_encoder = networks["movement_encoder"]
        self.text_encoder = networks["text_encoder"]
        self.motion_encoder = networks["motion_encoder"]
        self.vectorizer = vectorizer
        if mean.shape != (self.spec.feature_dim,) or std.shape != (self.spec.feature_dim,):
            raise ValueError(f"normalisation must be ({self.spec.feature_dim},), got {mean.shape} and {std.shape}")
        if np.any(std <= 0):
            raise ValueError("evaluator std has non-positive entries")
        # float64 as the reference's numpy normalisation; cast to float32 afterwards as its loader does.
        self.register_buffer("mean", torch.as_tensor(mean, dtype=torch.float64), persistent=False)
        self.register_buffer("std", torch.as_tensor(std, dtype=torch.float64), persistent=False)
        self.checkpoint_epoch: int | None = None
        self.eval()

    @classmethod
    def from_files(cls, checkpoint_dir: str | Path, glove_dir: str | Path, dataset: str = "t2m",
                   device: str | torch.device = "cpu", *, norm_dir: str | Path | None = None,
                   allow_pickle: bool = False) -> T2MEvaluator:
        """Load the published checkpoint (strictly), GloVe vectorizer and evaluator normalisation.

        See :func:`resolve_t2m_files` for where each file is looked up. ``allow_pickle`` lets ``torch.load`` run
        arbitrary pickled code (needed only if the checkpoint holds non-tensor objects; off by default).
        """
        files = resolve_t2m_files(checkpoint_dir, glove_dir, dataset, norm_dir)
        spec = _dataset_spec(dataset)
        evaluator = cls(dataset, WordVectorizer.from_dir(files.glove_vectors.parent),
                        _load_norm(files.mean, spec), _load_norm(files.std, spec))
        evaluator.load_checkpoint(_load_checkpoint(files.checkpoint, allow_pickle), source=str(files.checkpoint))
        log.info("loaded T2M evaluator %s (epoch %s)", files.checkpoint, evaluator.checkpoint_epoch)
        return evaluator.to(device)

    def load_checkpoint(self, checkpoint: dict, *, source: str = "<checkpoint>") -> None:
        """Strictly load the three networks from a ``finest.tar`` dict; a naming or shape drift is an error."""
        for name in ("movement_encoder", "text_encoder", "motion_encoder"):
            try:
                getattr(self, name).load_state_dict(checkpoint[name], strict=True)
            except RuntimeError as exc:
                raise ValueError(f"{source}: entry {name!r} does not match the published architecture: {exc}") from exc
        epoch = checkpoint.get("epoch")
        self.checkpoint_epoch = int(epoch) if epoch is not None else None

    def train(self, mode: bool = True) -> T2MEvaluator:
        # A frozen published evaluator: dropout must never be active, whatever a caller's model.train() reaches.
        return super().train(False)

    @property
    def device(self) -> torch.device:
        return self.mean.device

    def normalized_window(self, features_raw: torch.Tensor, lengths: torch.Tensor, *, keep_padding: bool = False,
                          normalized: bool = False) -> torch.Tensor:
        """Raw (B, T, D) features -> evaluator-normalised float32 (B, T', D), zero at every frame >= length.

        T' = max(196, longest length): the reference always feeds 196-frame windows zero-padded after the clip (GT
        loader) and the convolutions see a few frames past each length, so this window makes embeddings equal to
        the reference's and independent of how the caller padded.

        keep_padding: the frames the caller gives past each length are kept (normalised like the others), as the
        reference's generated motions, sampled over the whole 196-frame window; frames beyond ``T`` are still zero.
        normalized: the input is already in the space the networks read (the evaluator's normalisation is skipped).
        """
        window = max(self.spec.max_motion_length, int(lengths.max()))
        x = features_raw[:, :window].to(self.device, torch.float64)
        if not normalized:
            x = (x - self.mean) / self.std
        if not keep_padding:
            valid = torch.arange(x.shape[1], device=self.device)[None, :] < lengths.to(self.device)[:, None]
            x = torch.where(valid[..., None], x, torch.zeros((), dtype=x.dtype, device=x.device))
        out = x.new_zeros(x.shape[0], window, x.shape[2])
        out[:, : x.shape[1]] = x
        return out.float()

    def _check_motion_batch(self, features: torch.Tensor, lengths: torch.Tensor) -> None:
        if features.ndim != 3 or features.shape[0] == 0 or features.shape[-1] != self.spec.feature_dim:
            raise ValueError(f"{self.spec.name} evaluator expects a non-empty batch of features "
                             f"(B, T, {self.spec.feature_dim}), got {tuple(features.shape)}")
        if lengths.shape != (features.shape[0],):
            raise ValueError(f"lengths must be ({features.shape[0]},), got {tuple(lengths.shape)}")
        if int(lengths.min()) < self.spec.unit_length or int(lengths.max()) > features.shape[1]:
            raise ValueError(f"lengths must lie in [{self.spec.unit_length}, {features.shape[1]}] frames, "
                             f"got min {int(lengths.min())} max {int(lengths.max())}")

    @torch.no_grad()
    def encode_motions(self, features_raw: torch.Tensor | np.ndarray,
                       lengths: torch.Tensor | np.ndarray | Sequence[int], *, keep_padding: bool = False,
                       normalized: bool = False) -> torch.Tensor:
        """Raw Guo features (B, T, D) with valid lengths (B,) -> motion embeddings (B, 512), in input order.
        ``keep_padding`` / ``normalized``: see :meth:`normalized_window` (default: zero past each length, the
        reference's ground-truth padding)."""
        features = torch.as_tensor(features_raw)
        lengths = torch.as_tensor(lengths, dtype=torch.int64).reshape(-1)
        self._check_motion_batch(features, lengths)
        window = self.normalized_window(features, lengths, keep_padding=keep_padding, normalized=normalized)
        movements = self.movement_encoder(window[..., :-4])  # foot contacts are not seen by the evaluator
        return self.motion_encoder(movements, lengths // self.spec.unit_length)

    @torch.no_grad()
    def encode_texts(self, token_lists: Sequence[Sequence[str]], lengths: str = "sentence") -> torch.Tensor:
        """Captions as lists of ``word/POS`` tokens -> text embeddings (B, 512), in input order; ``lengths``: the
        caption length rule (CAPTION_LENGTHS)."""
        word_embs, pos_onehot, sent_lens = self.vectorizer.encode_batch(token_lists, lengths)
        return self.encode_word_features(word_embs, pos_onehot, sent_lens)

    @torch.no_grad()
    def encode_word_features(self, word_embs: torch.Tensor, pos_onehot: torch.Tensor,
                             sent_lens: torch.Tensor) -> torch.Tensor:
        """Already-vectorised captions (B, 22, 300), (B, 15-class one-hots), (B,) -> (B, 512), in input order."""
        return self.text_encoder(word_embs.to(self.device, torch.float32), pos_onehot.to(self.device, torch.float32),
                                 sent_lens)
