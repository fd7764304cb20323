import hashlib
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from mfm.text import (
    MDM_CONTEXT_LENGTH,
    RANDOM_INIT_SHA256,
    TEXT_ENCODERS,
    TextEncoding,
    build_matching_text_encoder,
    build_text_encoder,
    minilm_default_folder,
)

WALK = "a person walks forward slowly"
WALK_PARAPHRASE = "someone is walking ahead"
BACKFLIP = "a man does a backflip"
LONG = ("a person walks forward slowly, then turns around to the left, raises both arms above the head, "
        "jumps twice in place and finally sits down on a chair near the wall")
CAPTIONS = [WALK, WALK_PARAPHRASE, BACKFLIP, LONG, ""]


def file_sha256(path) -> str:
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


def cosine(a: np.ndarray, b: np.ndarray) -> float:
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


# --------------------------------------------------------------------------------------------- registry


def test_unknown_encoder_lists_known_names():
    with pytest.raises(ValueError, match="unknown text encoder 'bert-xl'") as info:
        build_text_encoder("bert-xl")
    for name in TEXT_ENCODERS:
        assert name in str(info.value)


def test_import_does_not_load_heavy_libraries():
    code = "import sys, mfm.text; print(sorted(m for m in ('transformers', 'open_clip') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_text_encoding_rejects_inconsistent_shapes():
    with pytest.raises(ValueError, match="tokens must be"):
        TextEncoding(np.zeros((2, 4), np.float32), np.zeros((3, 5, 4), np.float32), np.zeros(3, np.int32))
    with pytest.raises(ValueError, match="together"):
        TextEncoding(np.zeros((2, 4), np.float32), np.zeros((2, 5, 4), np.float32), None)


# --------------------------------------------------------------------------------------------- minilm


@pytest.fixture(scope="module")
def minilm():
    return build_text_encoder("minilm")


def test_minilm_identity(minilm):
    assert minilm.id == "minilm" and minilm.dim == 384
    assert minilm.weights_sha256 == file_sha256(minilm_default_folder() / "model.safetensors")


def test_minilm_pooled_shapes_unit_norm_and_determinism(minilm):
    first = minilm.encode(CAPTIONS)
    assert first.pooled.shape == (len(CAPTIONS), 384) and first.pooled.dtype == np.float32
    assert first.tokens is None and first.token_lengths is None
    np.testing.assert_allclose(np.linalg.norm(first.pooled, axis=1), 1.0, atol=1e-5)
    again = minilm.encode(CAPTIONS)
    np.testing.assert_array_equal(first.pooled, again.pooled)


def test_minilm_batch_size_does_not_change_results(minilm):
    whole = minilm.encode(CAPTIONS, batch_size=64).pooled
    one_by_one = minilm.encode(CAPTIONS, batch_size=1).pooled
    np.testing.assert_allclose(whole, one_by_one, atol=1e-5)


def test_minilm_matches_sentence_transformers(minilm):
    from sentence_transformers import SentenceTransformer

    reference = SentenceTransformer(str(minilm_default_folder()), device="cpu").encode(CAPTIONS)
    np.testing.assert_allclose(minilm.encode(CAPTIONS).pooled, reference, atol=1e-5)


def test_minilm_similarities_are_semantic(minilm):
    walk, paraphrase, backflip = minilm.encode([WALK, WALK_PARAPHRASE, BACKFLIP]).pooled
    assert cosine(walk, paraphrase) == pytest.approx(0.775, abs=0.005)
    assert cosine(walk, backflip) == pytest.approx(0.207, abs=0.005)
    assert cosine(walk, paraphrase) > cosine(walk, backflip) + 0.4


def test_minilm_token_features(minilm):
    # WordPiece: [CLS] a person walks forward slowly [SEP] = 7; [CLS] someone is walking ahead [SEP] = 6.
    out = minilm.encode([WALK, WALK_PARAPHRASE, LONG], token_features=True, max_tokens=8)
    assert out.tokens.shape == (3, 8, 384) and out.tokens.dtype == np.float32
    assert out.token_lengths.dtype == np.int32
    np.testing.assert_array_equal(out.token_lengths, [7, 6, 8])
    assert not out.tokens[0, 7:].any() and not out.tokens[1, 6:].any()
    assert np.abs(out.tokens[2]).sum(axis=1).all()  # truncated text: all 8 positions are real tokens
    # Untruncated texts: pooled is the normalised mean of exactly these token features.
    for i in (0, 1):
        mean = out.tokens[i, :out.token_lengths[i]].mean(axis=0)
        np.testing.assert_allclose(mean / np.linalg.norm(mean), out.pooled[i], atol=1e-5)
    np.testing.assert_array_equal(out.pooled, minilm.encode([WALK, WALK_PARAPHRASE, LONG]).pooled)


def test_minilm_empty_and_invalid_inputs(minilm):
    empty = minilm.encode([], token_features=True, max_tokens=4)
    assert empty.pooled.shape == (0, 384) and empty.tokens.shape == (0, 4, 384)
    with pytest.raises(TypeError, match="list of strings"):
        minilm.encode(WALK)
    with pytest.raises(ValueError, match="max_tokens"):
        minilm.encode([WALK], token_features=True, max_tokens=0)


def test_minilm_weights_folder_must_exist(tmp_path):
    with pytest.raises(FileNotFoundError, match="sentence-transformers model folder"):
        build_text_encoder("minilm", weights=tmp_path / "missing")
    with pytest.raises(FileNotFoundError, match="modules.json"):
        build_text_encoder("minilm", weights=tmp_path)


def test_build_matching_text_encoder_checks_the_weights(minilm):
    entry = {"id": "minilm", "dim": 384, "weights_sha256": minilm.weights_sha256, "options": {}}
    rebuilt = build_matching_text_encoder(entry)
    np.testing.assert_array_equal(rebuilt.encode([WALK]).pooled, minilm.encode([WALK]).pooled)
    with pytest.raises(ValueError, match="is not the dataset's"):
        build_matching_text_encoder({**entry, "weights_sha256": "0" * 64})


# --------------------------------------------------------------------------------------------- CLIP


@pytest.fixture(scope="module")
def clip_random():
    return build_text_encoder("clip-vit-b-32", allow_random=True)


@pytest.fixture(scope="module")
def open_clip_model():
    """A full open_clip CLIP ViT-B-32 (random, QuickGELU like OpenAI's): the reference for encode_text."""
    import open_clip

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(1)
        return open_clip.create_model("ViT-B-32", pretrained=None, force_quick_gelu=True).eval()


@pytest.fixture(scope="module")
def open_clip_checkpoint(open_clip_model, tmp_path_factory):
    from safetensors.torch import save_file

    path = tmp_path_factory.mktemp("clip") / "vit_b_32_full.safetensors"
    save_file({k: v.contiguous() for k, v in open_clip_model.state_dict().items()}, str(path))
    return path


def mdm_tokens(texts: list[str], context_length: int) -> torch.Tensor:
    """MDM's encode_text input: clip.tokenize(context_length, truncate=True) zero-padded to 77."""
    import open_clip

    ids = open_clip.tokenize(texts, context_length=context_length)
    return torch.nn.functional.pad(ids, (0, 77 - context_length))


def test_clip_needs_weights_or_explicit_random():
    with pytest.raises(ValueError, match="needs weights.*openai.*allow_random"):
        build_text_encoder("clip-vit-b-32")


def test_clip_missing_file_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="CLIP weights file not found.*openai"):
        build_text_encoder("clip-vit-b-32", weights=tmp_path / "nope.pt")


def test_clip_openai_offline_without_cache_is_a_clear_error():
    from huggingface_hub import try_to_load_from_cache

    if os.environ.get("HF_HUB_OFFLINE") != "1":
        pytest.skip("needs HF_HUB_OFFLINE=1 (otherwise a failed download retries for ~1 min)")
    repo = "timm/vit_base_patch32_clip_224.openai"
    if any(isinstance(try_to_load_from_cache(repo, f), str)
           for f in ("open_clip_model.safetensors", "open_clip_pytorch_model.bin")):
        pytest.skip("OpenAI ViT-B-32 weights are in the local cache; the offline error cannot happen")
    with pytest.raises(RuntimeError, match="not in open_clip's cache.*local"):
        build_text_encoder("clip-vit-b-32", weights="openai")


def test_clip_random_pooled_is_the_eot_token_feature(clip_random):
    assert clip_random.id == "clip-vit-b-32" and clip_random.dim == 512
    assert clip_random.weights_sha256 == RANDOM_INIT_SHA256
    out = clip_random.encode(CAPTIONS, token_features=True, max_tokens=77, batch_size=2)
    assert out.pooled.shape == (len(CAPTIONS), 512) and out.pooled.dtype == np.float32
    assert out.tokens.shape == (len(CAPTIONS), 77, 512)
    ids = clip_random.tokenize(CAPTIONS)
    np.testing.assert_array_equal(out.token_lengths, (ids != 0).sum(1).numpy())
    assert out.token_lengths[-1] == 2  # "" -> SOT EOT
    for i, length in enumerate(out.token_lengths):
        np.testing.assert_allclose(out.tokens[i, length - 1], out.pooled[i], atol=1e-5)
        assert not out.tokens[i, length:].any()
    np.testing.assert_array_equal(clip_random.encode(CAPTIONS, batch_size=2).pooled, out.pooled)  # deterministic
    # Other batch sizes change BLAS blocking, so only float rounding may differ.
    np.testing.assert_allclose(clip_random.encode(CAPTIONS, batch_size=64).pooled, out.pooled, atol=1e-5)


def test_clip_token_features_are_cut_to_max_tokens(clip_random):
    out = clip_random.encode([WALK, LONG], token_features=True, max_tokens=4)
    np.testing.assert_array_equal(out.token_lengths, [4, 4])
    full = clip_random.encode([WALK, LONG], token_features=True, max_tokens=77)
    np.testing.assert_allclose(out.tokens, full.tokens[:, :4], atol=1e-6)


def test_clip_random_init_is_reproducible_and_leaves_global_rng_alone(clip_random):
    torch.manual_seed(123)
    expected_next = torch.rand(3)
    torch.manual_seed(123)
    entry = {"id": "clip-vit-b-32", "dim": 512, "weights_sha256": RANDOM_INIT_SHA256, "options": {}}
    rebuilt = build_matching_text_encoder(entry, allow_random=True)
    torch.testing.assert_close(torch.rand(3), expected_next)
    np.testing.assert_array_equal(rebuilt.encode([WALK]).pooled, clip_random.encode([WALK]).pooled)


@pytest.fixture(scope="module")
def encode_text_reference(open_clip_model):
    """open_clip's own encode_text on MDM-style tokens, per context length."""
    with torch.inference_mode():
        return {n: open_clip_model.encode_text(mdm_tokens(CAPTIONS, n)).numpy() for n in (77, MDM_CONTEXT_LENGTH)}


@pytest.mark.parametrize("context_length", [77, MDM_CONTEXT_LENGTH])
def test_clip_from_full_checkpoint_matches_open_clip_encode_text(open_clip_checkpoint, encode_text_reference,
                                                                 context_length):
    encoder = build_text_encoder("clip-vit-b-32", weights=open_clip_checkpoint, context_length=context_length)
    assert encoder.weights_sha256 == file_sha256(open_clip_checkpoint)
    assert encoder.options == {"context_length": context_length, "quick_gelu": True}
    out = encoder.encode(CAPTIONS, token_features=True, max_tokens=77)
    np.testing.assert_allclose(out.pooled, encode_text_reference[context_length], atol=1e-5)
    eot = out.token_lengths[CAPTIONS.index(LONG)] - 1
    np.testing.assert_allclose(out.tokens[CAPTIONS.index(LONG), eot], out.pooled[CAPTIONS.index(LONG)], atol=1e-5)
    if context_length == MDM_CONTEXT_LENGTH:
        # MDM truncation: LONG is cut to 22 tokens, its embedding changes; short captions are unaffected.
        assert out.token_lengths[CAPTIONS.index(LONG)] == MDM_CONTEXT_LENGTH
        short = [CAPTIONS.index(c) for c in (WALK, WALK_PARAPHRASE, BACKFLIP)]
        np.testing.assert_allclose(out.pooled[short], encode_text_reference[77][short], atol=1e-5)
        long_diff = out.pooled[CAPTIONS.index(LONG)] - encode_text_reference[77][CAPTIONS.index(LONG)]
        assert np.abs(long_diff).max() > 1e-3


@pytest.mark.parametrize("kind", ["text_only_state_dict", "torchscript"])
def test_clip_loads_text_only_and_torchscript_checkpoints(open_clip_model, encode_text_reference, tmp_path, kind):
    path = tmp_path / f"{kind}.pt"
    if kind == "text_only_state_dict":
        # open_clip training checkpoints: {"state_dict": {"module.<key>": ...}}, here the text tower only.
        text_state = {k: v for k, v in open_clip_model.state_dict().items() if not k.startswith("visual.")}
        torch.save({"epoch": 3, "state_dict": {f"module.{k}": v for k, v in text_state.items()}}, path)
    else:
        # OpenAI's ViT-B-32.pt is a TorchScript archive of the whole CLIP with open_clip's key names.
        with torch.no_grad():
            traced = torch.jit.trace_module(open_clip_model, {"encode_text": mdm_tokens([WALK], 77)},
                                            check_trace=False)
        torch.jit.save(traced, str(path))
    encoder = build_text_encoder("clip-vit-b-32", weights=path)
    assert encoder.weights_sha256 == file_sha256(path)
    np.testing.assert_allclose(encoder.encode(CAPTIONS).pooled, encode_text_reference[77], atol=1e-5)


def test_clip_rejects_a_checkpoint_of_another_model(tmp_path):
    wrong = tmp_path / "wrong.pt"
    torch.save({"token_embedding.weight": torch.zeros(10, 8)}, wrong)
    with pytest.raises(ValueError, match="wrong.pt: not a ViT-B-32 CLIP"):
        build_text_encoder("clip-vit-b-32", weights=wrong)
    garbage = tmp_path / "garbage.safetensors"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="garbage.safetensors: cannot read CLIP weights"):
        build_text_encoder("clip-vit-b-32", weights=garbage)


def test_minilm_takes_a_hub_id_found_in_the_hugging_face_cache(minilm, tmp_path, monkeypatch):
    """A hub id resolves through the Hugging Face cache (offline here: cache only); the same weights give the same
    encoder hash and embeddings as the shipped folder. A missing one names the cache and what to do."""
    import shutil

    from huggingface_hub import constants

    from mfm.text import minilm_default_folder

    cache = tmp_path / "hub"
    repo = cache / "models--sentence-transformers--all-MiniLM-L6-v2"
    snapshot = repo / "snapshots" / "0123456789abcdef0123456789abcdef01234567"
    shutil.copytree(minilm_default_folder(), snapshot)
    (repo / "refs").mkdir()
    (repo / "refs" / "main").write_text("0123456789abcdef0123456789abcdef01234567")
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(cache))
    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    for name in ("sentence-transformers/all-MiniLM-L6-v2", "all-MiniLM-L6-v2"):
        from_hub = build_text_encoder("minilm", weights=name)
        assert from_hub.weights_sha256 == minilm.weights_sha256
        np.testing.assert_array_equal(from_hub.encode(["a person waves"]).pooled,
                                      minilm.encode(["a person waves"]).pooled)
    with pytest.raises(FileNotFoundError, match=r"'sentence-transformers/paraphrase-MiniLM-L3-v2' are not in the "
                                                r"Hugging Face cache .*hub.*pass a local folder"):
        build_text_encoder("minilm", weights="paraphrase-MiniLM-L3-v2")
