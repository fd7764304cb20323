"""Evaluators: the official T2M networks load a checkpoint laid out like the published one, and our motion-CLIP
evaluator trains, saves and loads."""

from __future__ import annotations

import hashlib
import math
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.nn.utils.rnn import pack_padded_sequence

from mfm.evaluators import (
    POS_CLASSES,
    ActionClassifier,
    ContrastiveEvaluator,
    ContrastiveEvaluatorConfig,
    T2MEvaluator,
    T2MEvaluatorFilesMissing,
    WordVectorizer,
    duplicate_caption_mask,
    infonce_loss,
    load_evaluator,
    retrieval_accuracy,
    save_evaluator,
    t2m_dataset_for_skeleton,
)
from mfm.evaluators.t2m import build_t2m_networks, sentence_tokens

# Small tensors: one thread avoids OpenMP spin-waits on a shared 2-core machine (3x faster there).
pytestmark = pytest.mark.usefixtures("single_thread")


# ----------------------------------------------------------------------------------------------------------------------
# Official T2M evaluator

# Written by hand from EricGuo5513/text-to-motion networks/modules.py + evaluator_wrapper.py (dim_pose 263 -> 259 after
# dropping the foot contacts, movement 512, motion hidden 1024, text hidden 512, co-embedding 512, word 300, POS 15),
# so a renamed attribute or a changed size fails here rather than at the user's strict load.
GRU_SUFFIXES = ("weight_ih_l0", "weight_hh_l0", "bias_ih_l0", "bias_hh_l0")
PUBLISHED_T2M_SHAPES = {
    "movement_encoder": {
        "main.0.weight": (512, 259, 4), "main.0.bias": (512,),
        "main.3.weight": (512, 512, 4), "main.3.bias": (512,),
        "out_net.weight": (512, 512), "out_net.bias": (512,),
    },
    "text_encoder": {
        "hidden": (2, 1, 512),
        "pos_emb.weight": (300, 15), "pos_emb.bias": (300,),
        "input_emb.weight": (512, 300), "input_emb.bias": (512,),
        "gru.weight_ih_l0": (1536, 512), "gru.weight_hh_l0": (1536, 512),
        "gru.bias_ih_l0": (1536,), "gru.bias_hh_l0": (1536,),
        "gru.weight_ih_l0_reverse": (1536, 512), "gru.weight_hh_l0_reverse": (1536, 512),
        "gru.bias_ih_l0_reverse": (1536,), "gru.bias_hh_l0_reverse": (1536,),
        "output_net.0.weight": (512, 1024), "output_net.0.bias": (512,),
        "output_net.1.weight": (512,), "output_net.1.bias": (512,),
        "output_net.3.weight": (512, 512), "output_net.3.bias": (512,),
    },
    "motion_encoder": {
        "hidden": (2, 1, 1024),
        "input_emb.weight": (1024, 512), "input_emb.bias": (1024,),
        "gru.weight_ih_l0": (3072, 1024), "gru.weight_hh_l0": (3072, 1024),
        "gru.bias_ih_l0": (3072,), "gru.bias_hh_l0": (3072,),
        "gru.weight_ih_l0_reverse": (3072, 1024), "gru.weight_hh_l0_reverse": (3072, 1024),
        "gru.bias_ih_l0_reverse": (3072,), "gru.bias_hh_l0_reverse": (3072,),
        "output_net.0.weight": (1024, 2048), "output_net.0.bias": (1024,),
        "output_net.1.weight": (1024,), "output_net.1.bias": (1024,),
        "output_net.3.weight": (512, 1024), "output_net.3.bias": (512,),
    },
}

VOCAB = ["sos", "eos", "unk", "a", "man", "person", "walk", "forward", "left", "quickly", "jump", "hand", "wave",
         "the", "circle", "in"]


def _shapes(module: torch.nn.Module) -> dict[str, tuple[int, ...]]:
    return {k: tuple(v.shape) for k, v in module.state_dict().items()}


def test_networks_have_the_published_key_names_and_shapes():
    networks = build_t2m_networks("t2m")
    for entry, expected in PUBLISHED_T2M_SHAPES.items():
        assert _shapes(networks[entry]) == expected, entry
    kit = build_t2m_networks("kit")
    assert _shapes(kit["movement_encoder"])["main.0.weight"] == (512, 247, 4)
    assert _shapes(kit["motion_encoder"]) == PUBLISHED_T2M_SHAPES["motion_encoder"]


def _write_glove(glove_dir: Path, seed: int = 0) -> np.ndarray:
    """GloVe files in the published format; rows deliberately not in word-list order (the index decides)."""
    rng = np.random.default_rng(seed)
    vectors = rng.standard_normal((len(VOCAB), 300))
    rows = rng.permutation(len(VOCAB))
    glove_dir.mkdir(parents=True, exist_ok=True)
    np.save(glove_dir / "our_vab_data.npy", vectors)
    with open(glove_dir / "our_vab_words.pkl", "wb") as f:
        pickle.dump(list(VOCAB), f)
    with open(glove_dir / "our_vab_idx.pkl", "wb") as f:
        pickle.dump({w: int(r) for w, r in zip(VOCAB, rows)}, f)
    return vectors[rows]  # row i = vector of VOCAB[i]


def _published_style_checkpoint(dataset: str = "t2m", seed: int = 0) -> dict:
    """A finest.tar dict with the published entries (+ optimiser states and counters, as the T2M trainer saves);
    weights at a trained-network scale so activations stay O(1)."""
    torch.manual_seed(seed)
    networks = build_t2m_networks(dataset)
    checkpoint = {name: {k: 0.05 * torch.randn_like(v) for k, v in net.state_dict().items()}
                  for name, net in networks.items()}
    checkpoint["opt_text_encoder"] = torch.optim.Adam(networks["text_encoder"].parameters()).state_dict()
    checkpoint["opt_motion_encoder"] = torch.optim.Adam(networks["motion_encoder"].parameters()).state_dict()
    checkpoint.update(epoch=7, iter=1234)
    return checkpoint


@pytest.fixture(scope="module")
def t2m_checkpoint() -> dict:
    return _published_style_checkpoint("t2m")


@pytest.fixture(scope="module")
def t2m_checkpoint_file(tmp_path_factory, t2m_checkpoint) -> Path:
    """Saved once (64 MB at the published sizes) and linked into each test's checkpoint folder."""
    path = tmp_path_factory.mktemp("ckpt") / "finest.tar"
    torch.save(t2m_checkpoint, path)
    return path


def _write_t2m_files(root: Path, checkpoint_file: Path, norm_layout: str = "flat", dataset: str = "t2m"):
    ckpt_dir, glove_dir = root / "checkpoints", root / "glove"
    model_dir = ckpt_dir / dataset / "text_mot_match" / "model"
    model_dir.mkdir(parents=True)
    (model_dir / "finest.tar").symlink_to(checkpoint_file)
    word_vectors = _write_glove(glove_dir)
    dim = 263 if dataset == "t2m" else 251
    rng = np.random.default_rng(1)
    mean, std = rng.standard_normal(dim) * 0.1, rng.uniform(0.5, 1.5, dim)
    if norm_layout == "flat":  # MDM: dataset/t2m_mean.npy copied beside the checkpoints
        norm_dir, names = ckpt_dir, (f"{dataset}_mean.npy", f"{dataset}_std.npy")
    elif norm_layout == "t2m_meta":  # the T2M repository's checkpoints/t2m/Comp_v6_KLD01/meta
        norm_dir, names = ckpt_dir / dataset / "Comp_v6_KLD01" / "meta", ("mean.npy", "std.npy")
    else:
        norm_dir, names = root / "norms", (f"{dataset}_mean.npy", f"{dataset}_std.npy")
    norm_dir.mkdir(parents=True, exist_ok=True)
    np.save(norm_dir / names[0], mean)
    np.save(norm_dir / names[1], std)
    return ckpt_dir, glove_dir, norm_dir, word_vectors, mean, std


@pytest.fixture(scope="module")
def t2m_setup(tmp_path_factory, t2m_checkpoint_file):
    root = tmp_path_factory.mktemp("t2m")
    ckpt_dir, glove_dir, _, word_vectors, mean, std = _write_t2m_files(root, t2m_checkpoint_file)
    evaluator = T2MEvaluator.from_files(ckpt_dir, glove_dir, "t2m")
    return evaluator, word_vectors, mean, std


def test_from_files_loads_the_checkpoint_strictly(t2m_setup, t2m_checkpoint):
    evaluator, _, mean, std = t2m_setup
    for entry in ("movement_encoder", "text_encoder", "motion_encoder"):
        loaded = getattr(evaluator, entry).state_dict()
        assert loaded.keys() == t2m_checkpoint[entry].keys()
        for key, value in t2m_checkpoint[entry].items():
            assert torch.equal(loaded[key], value), (entry, key)
    assert evaluator.checkpoint_epoch == 7
    assert not evaluator.training
    assert not evaluator.train().training  # frozen: dropout never switches on
    np.testing.assert_array_equal(evaluator.mean.numpy(), mean)
    np.testing.assert_array_equal(evaluator.std.numpy(), std)


@pytest.mark.parametrize("layout", ["t2m_meta", "norm_dir"])
def test_normalisation_is_found_in_either_published_layout(tmp_path, t2m_checkpoint_file, layout):
    ckpt_dir, glove_dir, norm_dir, _, mean, _ = _write_t2m_files(tmp_path, t2m_checkpoint_file, norm_layout=layout)
    evaluator = T2MEvaluator.from_files(ckpt_dir, glove_dir, "t2m", norm_dir=norm_dir if layout == "norm_dir" else None)
    np.testing.assert_array_equal(evaluator.mean.numpy(), mean)


def test_missing_files_are_all_named_with_where_to_get_them(tmp_path):
    with pytest.raises(T2MEvaluatorFilesMissing) as info:
        T2MEvaluator.from_files(tmp_path / "checkpoints", tmp_path / "glove", "kit")
    message = str(info.value)
    for name in ("kit/text_mot_match/model/finest.tar", "our_vab_data.npy", "our_vab_words.pkl", "our_vab_idx.pkl",
                 "kit_mean.npy", "kit_std.npy", "Comp_v6_KLD005/meta/mean.npy"):
        assert name in message, name
    assert "download_t2m_evaluators.sh" in message and "EricGuo5513/text-to-motion" in message
    assert isinstance(info.value, FileNotFoundError)


def test_missing_subset_lists_only_what_is_absent(tmp_path, t2m_checkpoint_file):
    ckpt_dir, glove_dir, *_ = _write_t2m_files(tmp_path, t2m_checkpoint_file)
    (glove_dir / "our_vab_idx.pkl").unlink()
    with pytest.raises(T2MEvaluatorFilesMissing) as info:
        T2MEvaluator.from_files(ckpt_dir, glove_dir, "t2m")
    assert [p.name for p in info.value.missing] == ["our_vab_idx.pkl"]


def test_a_renamed_key_is_rejected(tmp_path, t2m_checkpoint):
    drifted = dict(t2m_checkpoint)
    movement = dict(drifted["movement_encoder"])
    movement["main.2.weight"] = movement.pop("main.3.weight")
    drifted["movement_encoder"] = movement
    torch.save(drifted, tmp_path / "drifted.tar")
    ckpt_dir, glove_dir, *_ = _write_t2m_files(tmp_path, tmp_path / "drifted.tar")
    with pytest.raises(ValueError, match="movement_encoder"):
        T2MEvaluator.from_files(ckpt_dir, glove_dir, "t2m")


def test_kit_dataset_and_skeleton_names():
    assert t2m_dataset_for_skeleton("humanml3d") == "t2m" and t2m_dataset_for_skeleton("kit") == "kit"
    with pytest.raises(ValueError, match="no official T2M evaluator"):
        t2m_dataset_for_skeleton("smpl24")
    with pytest.raises(ValueError, match="unknown T2M evaluator dataset"):
        build_t2m_networks("humanact12")


def test_encode_motions_returns_input_order_and_ignores_padding_content(t2m_setup):
    evaluator, *_ = t2m_setup
    torch.manual_seed(0)
    lengths = torch.tensor([40, 196, 17, 100])  # unsorted: the reference would return them sorted by length
    features = torch.randn(4, 196, 263)
    batch = evaluator.encode_motions(features, lengths)
    assert batch.shape == (4, 512) and torch.isfinite(batch).all()
    for i, length in enumerate(lengths.tolist()):
        # Alone, cropped to its own length (no padding at all): the 196-frame window makes it identical.
        single = evaluator.encode_motions(features[i : i + 1, :length], [length])
        torch.testing.assert_close(batch[i : i + 1], single, rtol=1e-4, atol=1e-5)
    garbage = features.clone()
    for i, length in enumerate(lengths.tolist()):
        garbage[i, length:] = float("nan")
    torch.testing.assert_close(evaluator.encode_motions(garbage, lengths), batch, rtol=1e-4, atol=1e-5)


def test_encode_motions_matches_the_reference_wrapper_procedure(t2m_setup):
    """As EvaluatorModelWrapper.get_motion_embeddings fed by the GT loader: numpy float64 normalisation, zero padding
    to 196 frames, batch sorted by length, pack_padded_sequence(enforce_sorted=True), output in sorted order."""
    evaluator, _, mean, std = t2m_setup
    rng = np.random.default_rng(3)
    lengths = np.array([40, 196, 17, 100, 64])
    raw = rng.standard_normal((5, 196, 263)).astype(np.float32)
    padded = np.zeros((5, 196, 263))
    for i, n in enumerate(lengths):
        padded[i, :n] = (raw[i, :n] - mean) / std
    align = np.argsort(lengths)[::-1].copy()
    motions, m_lens = torch.tensor(padded[align]).float(), torch.tensor(lengths[align])
    encoder = evaluator.motion_encoder
    with torch.no_grad():
        movements = evaluator.movement_encoder(motions[..., :-4])
        packed = pack_padded_sequence(encoder.input_emb(movements), (m_lens // 4).tolist(), batch_first=True)
        _, last = encoder.gru(packed, encoder.hidden.repeat(1, 5, 1))
        reference_sorted = encoder.output_net(torch.cat([last[0], last[1]], dim=-1))
    ours = evaluator.encode_motions(raw, lengths)
    torch.testing.assert_close(ours[align], reference_sorted, rtol=1e-5, atol=1e-6)


def test_encode_motions_uses_all_but_the_foot_contacts(t2m_setup):
    evaluator, *_ = t2m_setup
    torch.manual_seed(1)
    features = torch.randn(1, 60, 263)
    base = evaluator.encode_motions(features, [60])
    contacts_changed = features.clone()
    contacts_changed[..., 259:] += 5.0
    torch.testing.assert_close(evaluator.encode_motions(contacts_changed, [60]), base)
    root_changed = features.clone()
    root_changed[..., 0] += 0.1
    assert not torch.allclose(evaluator.encode_motions(root_changed, [60]), base)


def test_encode_motions_rejects_bad_input(t2m_setup):
    evaluator, *_ = t2m_setup
    with pytest.raises(ValueError, match="263"):
        evaluator.encode_motions(torch.zeros(1, 40, 251), [40])
    with pytest.raises(ValueError, match="lengths must lie"):
        evaluator.encode_motions(torch.zeros(2, 40, 263), [40, 3])


def test_word_vectorizer_follows_the_reference_semantics(t2m_setup):
    evaluator, word_vectors, *_ = t2m_setup
    vectorizer = evaluator.vectorizer
    vec = {w: word_vectors[i].astype(np.float32) for i, w in enumerate(VOCAB)}

    def pos_of(token):
        return POS_CLASSES[int(np.argmax(vectorizer.lookup(token)[1]))]

    assert pos_of("man/NOUN") == "NOUN" and pos_of("a/DET") == "DET"
    assert pos_of("walk/VERB") == "Act_VIP"  # VIP lists override the tagger
    assert pos_of("left/VERB") == "Loc_VIP" and pos_of("hand/NOUN") == "Body_VIP"
    assert pos_of("quickly/ADV") == "Desc_VIP"
    assert pos_of("the/INTJ") == "OTHER"  # a tag outside the 15 classes
    np.testing.assert_array_equal(vectorizer.lookup("man/NOUN")[0], vec["man"])
    unknown_vec, unknown_pos = vectorizer.lookup("zebra/NOUN")  # unknown word: 'unk' vector, OTHER
    np.testing.assert_array_equal(unknown_vec, vec["unk"])
    assert POS_CLASSES[int(np.argmax(unknown_pos))] == "OTHER" and unknown_pos.sum() == 1
    with pytest.raises(ValueError, match="word/POS"):
        vectorizer.lookup("walk")

    words, onehots, sent_len = vectorizer.encode_sentence(["a/DET", "man/NOUN", "walk/VERB"])
    assert words.shape == (22, 300) and onehots.shape == (22, 15) and sent_len == 5
    np.testing.assert_array_equal(words[0], vec["sos"])
    np.testing.assert_array_equal(words[4], vec["eos"])
    np.testing.assert_array_equal(words[5:], np.repeat(vec["unk"][None], 17, axis=0))
    assert {POS_CLASSES[i] for i in onehots[[0, 4, 5, 21]].argmax(axis=1)} == {"OTHER"}

    long_tokens = [f"w{i}/NOUN" for i in range(25)]
    sentence, sent_len = sentence_tokens(long_tokens)
    assert sent_len == 22 and sentence == ["sos/OTHER", *long_tokens[:20], "eos/OTHER"]


def test_word_vectorizer_rejects_an_inconsistent_vocabulary():
    vectors = np.zeros((3, 300))
    with pytest.raises(ValueError, match="no 'unk' entry"):
        WordVectorizer(vectors, ["sos", "eos", "man"], {"sos": 0, "eos": 1, "man": 2})
    with pytest.raises(ValueError, match="no index entry"):
        WordVectorizer(vectors, ["sos", "eos", "unk", "man"], {"sos": 0, "eos": 1, "unk": 2})
    with pytest.raises(ValueError, match=r"\(N, 300\)"):
        WordVectorizer(np.zeros((3, 50)), ["sos", "eos", "unk"], {"sos": 0, "eos": 1, "unk": 2})


def test_vocabulary_pickles_cannot_run_code(tmp_path):
    _write_glove(tmp_path)
    assert len(WordVectorizer.from_dir(tmp_path)) == len(VOCAB)
    with open(tmp_path / "our_vab_words.pkl", "wb") as f:
        pickle.dump(Path("/etc"), f)  # any class reference is refused before it is resolved
    with pytest.raises(ValueError, match="refusing to load"):
        WordVectorizer.from_dir(tmp_path)


def test_encode_texts_returns_input_order(t2m_setup):
    evaluator, *_ = t2m_setup
    captions = [
        ["a/DET", "man/NOUN"],
        ["a/DET", "person/NOUN", "walk/VERB", "forward/ADV", "in/ADP", "a/DET", "circle/NOUN", "quickly/ADV"],
        ["the/DET", "person/NOUN", "wave/VERB", "left/ADJ", "hand/NOUN"],
    ]
    batch = evaluator.encode_texts(captions)
    assert batch.shape == (3, 512) and torch.isfinite(batch).all()
    for i, caption in enumerate(captions):
        torch.testing.assert_close(batch[i : i + 1], evaluator.encode_texts([caption]), rtol=1e-4, atol=1e-5)
    assert not torch.allclose(batch[0], batch[1])
    with pytest.raises(TypeError, match="list of token lists"):
        evaluator.encode_texts(["a/DET", "man/NOUN"])


def test_real_clip_with_real_evaluator_norms(reference_data, t2m_checkpoint_file, tmp_path):
    """The published normalisation files load and the real clip 012314 (170 frames) encodes to a finite vector."""
    norms = reference_data / "evaluator-norms"
    ckpt_dir, glove_dir, *_ = _write_t2m_files(tmp_path, t2m_checkpoint_file, norm_layout="norm_dir")
    evaluator = T2MEvaluator.from_files(ckpt_dir, glove_dir, "t2m", norm_dir=norms)
    # The root and contact groups of the evaluator std carry the /25 (reference notes §4.6).
    train_std = np.load(reference_data / "humanml3d" / "Std.npy")
    assert 20 < train_std[0] / evaluator.std[0].item() < 30
    features = np.load(reference_data / "humanml3d" / "new_joint_vecs_012314.npy")[None]
    emb = evaluator.encode_motions(features, [features.shape[1]])
    assert emb.shape == (1, 512) and torch.isfinite(emb).all()


# ----------------------------------------------------------------------------------------------------------------------
# Our contrastive evaluator


def _tiny_config(**overrides) -> ContrastiveEvaluatorConfig:
    values = dict(feature_dim=8, text_dim=16, latent_dim=32, num_layers=1, num_heads=2, ff_dim=64, dropout=0.0,
                  out_dim=16, text_hidden_dim=32)
    values.update(overrides)
    return ContrastiveEvaluatorConfig(**values)


def test_infonce_matches_a_hand_computation():
    motion = torch.tensor([[1.0, 0.0], [0.6, 0.8], [0.0, 2.0]])
    text = torch.tensor([[2.0, 0.0], [0.0, 1.0], [-1.0, 1.0]])
    tau = 0.5

    def unit(v):
        n = math.hypot(*v)
        return [x / n for x in v]

    m = [unit(r) for r in motion.tolist()]
    t = [unit(r) for r in text.tolist()]
    s = [[(m[i][0] * t[j][0] + m[i][1] * t[j][1]) / tau for j in range(3)] for i in range(3)]

    def ce(rows, allowed=lambda i, j: True):
        return sum(-rows[i][i] + math.log(sum(math.exp(rows[i][j]) for j in range(3) if allowed(i, j)))
                   for i in range(3)) / 3

    columns = [[s[j][i] for j in range(3)] for i in range(3)]
    expected = 0.5 * (ce(s) + ce(columns))
    assert infonce_loss(motion, text, tau).item() == pytest.approx(expected, rel=1e-6)

    # Ignoring the (0, 2) / (2, 0) pairs removes them from every softmax they appear in.
    ignore = torch.zeros(3, 3, dtype=torch.bool)
    ignore[0, 2] = ignore[2, 0] = True
    allowed = lambda i, j: not ignore[i, j]  # noqa: E731
    expected_filtered = 0.5 * (ce(s, allowed) + ce(columns, allowed))
    assert infonce_loss(motion, text, tau, ignore_negatives=ignore).item() == pytest.approx(expected_filtered, rel=1e-6)
    with pytest.raises(ValueError, match="False diagonal"):
        infonce_loss(motion, text, tau, ignore_negatives=torch.eye(3, dtype=torch.bool))


def test_duplicate_caption_mask_uses_tmr_threshold():
    captions = torch.tensor([[1.0, 0.0], [2.0, 0.1], [0.0, 1.0], [0.7, 0.7]])
    mask = duplicate_caption_mask(captions, 0.8)  # cosine > 0.6
    expected = torch.zeros(4, 4, dtype=torch.bool)
    for i, j in [(0, 1), (0, 3), (1, 3), (2, 3)]:
        expected[i, j] = expected[j, i] = True
    assert torch.equal(mask, expected)
    assert not duplicate_caption_mask(captions, 1.0).any()


def test_motion_encoder_is_padding_invariant():
    for pooling in ("cls", "mean"):
        torch.manual_seed(0)
        model = ContrastiveEvaluator(_tiny_config(pooling=pooling)).eval()
        lengths = torch.tensor([5, 9, 3])
        short = torch.randn(3, 9, 8)
        long = torch.full((3, 20, 8), float("nan"))
        long[:, :9] = short
        for i, n in enumerate(lengths.tolist()):
            long[i, n:] = float("nan")
        with torch.no_grad():
            a = model.encode_motions(short, lengths)
            b = model.encode_motions(long, lengths)
            alone = model.encode_motions(short[1:2, :9], lengths[1:2])
        assert torch.isfinite(b).all(), pooling
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(a[1:2], alone, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(a.norm(dim=-1), torch.ones(3))


def _paired_synthetic(n: int, generator: torch.Generator, w_motion: torch.Tensor, w_text: torch.Tensor):
    """Pairs sharing a latent z: motion frames = z @ w_motion (+ a per-frame wobble), text = z @ w_text (+ noise)."""
    z = torch.randn(n, w_motion.shape[0], generator=generator)
    frames = 12
    lengths = torch.randint(6, frames + 1, (n,), generator=generator)
    wobble = 0.3 * torch.sin(torch.arange(frames)[None, :, None] * 0.7 + torch.randn(n, 1, 1, generator=generator))
    motion = (z @ w_motion)[:, None, :] + wobble + 0.05 * torch.randn(n, frames, w_motion.shape[1], generator=generator)
    text = z @ w_text + 0.05 * torch.randn(n, w_text.shape[1], generator=generator)
    return motion, lengths, text


def test_training_on_separable_data_beats_chance():
    g = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    w_motion, w_text = torch.randn(4, 8, generator=g), torch.randn(4, 16, generator=g)
    train = _paired_synthetic(512, g, w_motion, w_text)
    held_out = _paired_synthetic(128, g, w_motion, w_text)
    model = ContrastiveEvaluator(_tiny_config(selfsim_threshold=None))

    def held_out_accuracy():
        model.eval()
        with torch.no_grad():
            m = model.encode_motions(held_out[0], held_out[1])
            t = model.encode_texts(held_out[2])
        model.train()
        return retrieval_accuracy(m, t, top_k=(1, 3), batch_size=32)

    before = held_out_accuracy()
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    for step in range(60):
        idx = torch.randint(0, 512, (64,), generator=g)
        loss = model.training_loss(train[0][idx], train[1][idx], train[2][idx])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    after = held_out_accuracy()
    chance_top1 = 1 / 32
    assert after[1] > 5 * chance_top1 and after[1] > before[1] + 0.1, (before, after)
    assert after[3] >= after[1]


def test_retrieval_accuracy_on_known_embeddings():
    torch.manual_seed(0)
    emb = torch.randn(64, 8)
    perfect = retrieval_accuracy(emb, emb * 3.0, top_k=(1, 2, 3))  # scale does not matter: cosine ranking
    assert perfect == {1: 1.0, 2: 1.0, 3: 1.0}
    shuffled = retrieval_accuracy(emb, emb[torch.randperm(64)], top_k=(1,))
    assert shuffled[1] < 0.3
    with pytest.raises(ValueError, match="at least batch_size"):
        retrieval_accuracy(emb[:10], emb[:10])


def test_save_load_round_trip_and_ids(tmp_path):
    torch.manual_seed(0)
    config = _tiny_config()
    model = ContrastiveEvaluator(config).eval()
    path = tmp_path / "evals" / "mclip.safetensors"
    evaluator_id = save_evaluator(path, model, config, "dataset-abc")
    assert evaluator_id == hashlib.sha256(path.read_bytes()).hexdigest()
    assert save_evaluator(tmp_path / "again.safetensors", model, config, "dataset-abc") == evaluator_id

    loaded = load_evaluator(path)
    assert loaded.evaluator_id == evaluator_id and loaded.manifest_dataset_id == "dataset-abc"
    assert loaded.kind == "contrastive"
    assert loaded.config == config and not loaded.model.training
    features, lengths, text = torch.randn(3, 10, 8), torch.tensor([10, 4, 7]), torch.randn(3, 16)
    with torch.no_grad():
        torch.testing.assert_close(loaded.model.encode_motions(features, lengths),
                                   model.encode_motions(features, lengths))
        torch.testing.assert_close(loaded.model.encode_texts(text), model.encode_texts(text))

    with torch.no_grad():
        model.text_head.mlp[0].bias.add_(1e-3)
    assert save_evaluator(tmp_path / "changed.safetensors", model, config, "dataset-abc") != evaluator_id

    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="does not match evaluator_id"):
        load_evaluator(path)
    with pytest.raises(FileNotFoundError, match="sidecar missing"):
        load_evaluator(tmp_path / "never-saved.safetensors")


def test_action_classifier_save_load(tmp_path):
    torch.manual_seed(0)
    config = _tiny_config(pooling="mean", out_dim=12)
    classifier = ActionClassifier(config, ["jump", "run", "walk"]).eval()
    features, lengths = torch.randn(2, 10, 8), torch.tensor([10, 6])
    with torch.no_grad():
        logits = classifier(features, lengths)
    assert logits.shape == (2, 3) and classifier.features(features, lengths).shape == (2, 12)
    path = tmp_path / "recogniser.safetensors"
    save_evaluator(path, classifier, config, "dataset-xyz")
    loaded = load_evaluator(path)
    assert loaded.kind == "action_classifier" and loaded.model.action_classes == ["jump", "run", "walk"]
    with torch.no_grad():
        torch.testing.assert_close(loaded.model(features, lengths), logits)


def test_config_validation():
    with pytest.raises(ValueError, match="divisible by num_heads"):
        _tiny_config(latent_dim=30, num_heads=4)
    with pytest.raises(ValueError, match="pooling"):
        _tiny_config(pooling="max")
    with pytest.raises(ValueError, match="unknown ContrastiveEvaluatorConfig keys"):
        ContrastiveEvaluatorConfig.from_dict({**_tiny_config().to_dict(), "layers": 3})
    assert ContrastiveEvaluatorConfig.from_dict(_tiny_config().to_dict()) == _tiny_config()
    manifest = {"feature_spec": {"dim": 251}, "text_encoder": {"id": "clip-vit-b-32", "dim": 512}}
    from_manifest = ContrastiveEvaluatorConfig.from_manifest(manifest, out_dim=512)
    assert (from_manifest.feature_dim, from_manifest.text_dim, from_manifest.out_dim) == (251, 512, 512)
    with pytest.raises(ValueError, match="text_encoder.dim"):
        ContrastiveEvaluatorConfig.from_manifest({"feature_spec": {"dim": 263}})
