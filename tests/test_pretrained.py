"""The diffusers-shaped MotionPipeline API (conventional names as aliases of ours, .to, generator=, output_type=,
save_pretrained) and the exported folder's Hub model card and file modes, on the tiny text run test_sample_cli.py
trains once per session."""

from __future__ import annotations

import json
import os
import re
import shutil
import stat
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from test_sample_cli import file_of, sample, text_run  # noqa: F401  (text_run: the session's tiny trained run)

from pipeline import checkpoint as ckpt
from pipeline.evaluation.job import table_rows
from pipeline.generation.inference import resolve_checkpoint
from pipeline.generation.integration import sample_seed
from pipeline.generation.pretrained import (
    ARGUMENT_ALIASES,
    MotionPipeline,
    export_pretrained,
    seed_from_generator,
)
from pipeline.generation.request import SamplingError

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("single_thread")]

PROMPTS = ["a person walks", "a person jumps"]


@pytest.fixture(scope="module")
def exported(text_run, tmp_path_factory) -> Path:  # noqa: F811
    return export_pretrained(text_run, tmp_path_factory.mktemp("export") / "model")


@pytest.fixture
def pipe(exported) -> MotionPipeline:
    return MotionPipeline.from_pretrained(exported, device="cpu")


def assert_same_motions(a, b, atol: float = 0.0) -> None:
    assert a.lengths == b.lengths and a.texts == b.texts
    for x, y in zip(a.features, b.features):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=0, atol=atol)


def card_metadata(card: str) -> tuple[dict, str]:
    """The YAML front matter of a model card and the Markdown after it."""
    match = re.match(r"^---\n(.*?)\n---\n(.*)$", card, flags=re.S)
    assert match, "the card does not open with a YAML front matter block"
    return yaml.safe_load(match.group(1)), match.group(2)


# ---------------------------------------------------------------------------------------------------------------
# the call's names


def test_the_conventional_names_give_the_same_motions_as_ours(pipe):
    ours = pipe(PROMPTS, lengths=[20, 24], num_samples=2, seed=3, steps=4, guidance=1.5)
    theirs = pipe(prompt=PROMPTS, lengths=[20, 24], num_motions_per_prompt=2, seed=3, num_inference_steps=4,
                  guidance_scale=1.5)
    assert_same_motions(ours, theirs)
    assert [r["nfe"] for r in theirs.records] == [r["nfe"] for r in ours.records]
    # and they do reach the sampler: another step count or scale gives other motions
    other = pipe(prompt=PROMPTS, lengths=[20, 24], num_motions_per_prompt=2, seed=3, num_inference_steps=2,
                 guidance_scale=1.5)
    assert not np.allclose(other.features[0], ours.features[0])
    # a single prompt string, as diffusers takes it
    single = pipe(prompt=PROMPTS[0], lengths=20, seed=3, num_inference_steps=4, guidance_scale=1.5)
    np.testing.assert_allclose(single.features[0], ours.features[0], rtol=0, atol=1e-5)  # another batch: rounding


@pytest.mark.parametrize(("theirs", "ours"), sorted(ARGUMENT_ALIASES.items()))
def test_both_names_of_one_argument_is_a_type_error(pipe, theirs, ours):
    values = {"texts": PROMPTS, "num_samples": 1, "steps": 2, "guidance": 1.0, "seed": 0,
              "prompt": PROMPTS, "num_motions_per_prompt": 1, "num_inference_steps": 2, "guidance_scale": 1.0,
              "generator": torch.Generator().manual_seed(0)}
    with pytest.raises(TypeError, match=f"both {ours}= and {theirs}="):
        pipe(lengths=20, **{ours: values[ours], theirs: values[theirs]})


def test_output_type_torch_holds_the_numpy_values(pipe):
    as_numpy = pipe(prompt=PROMPTS, lengths=20, seed=1, num_inference_steps=2, output_type="np")
    as_torch = pipe(prompt=PROMPTS, lengths=20, seed=1, num_inference_steps=2, output_type="pt")
    assert all(isinstance(f, np.ndarray) for f in as_numpy.features + as_numpy.joints)
    assert all(isinstance(f, torch.Tensor) and f.dtype == torch.float32 for f in as_torch.features + as_torch.joints)
    for a, b in zip(as_numpy.features + as_numpy.joints, as_torch.features + as_torch.joints):
        np.testing.assert_array_equal(a, b.numpy())
    assert_same_motions(as_numpy, pipe(PROMPTS, lengths=20, seed=1, steps=2, output_type="torch"))
    with pytest.raises(ValueError, match="output_type 'pil'"):
        pipe(prompt=PROMPTS, lengths=20, output_type="pil")


# ---------------------------------------------------------------------------------------------------------------
# generator=


def test_a_generator_stands_for_the_seed_it_draws_and_advances(pipe):
    request = {"prompt": PROMPTS, "num_motions_per_prompt": 2, "num_inference_steps": 2}  # lengths drawn too
    first = pipe(generator=torch.Generator().manual_seed(11), **request)
    again = pipe(generator=torch.Generator().manual_seed(11), **request)
    assert_same_motions(first, again)  # same generator state -> same motions
    seeded = pipe(seed=seed_from_generator(torch.Generator().manual_seed(11)), **request)
    assert_same_motions(first, seeded)  # the documented equivalence with seed=
    generator = torch.Generator().manual_seed(11)
    pipe(generator=generator, **request)
    advanced = pipe(generator=generator, **request)  # a used generator gives new motions, as in diffusers
    assert not np.allclose(advanced.features[0][:5], first.features[0][:5])


def test_one_generator_per_motion_is_the_seed_mechanism_with_the_callers_generators(pipe):
    ours = pipe(PROMPTS, lengths=[20, 24], num_samples=2, seed=3, steps=2)
    generators = [torch.Generator().manual_seed(sample_seed(3, i)) for i in range(4)]
    theirs = pipe(prompt=PROMPTS, lengths=[20, 24], num_motions_per_prompt=2, num_inference_steps=2,
                  generator=generators)
    assert_same_motions(ours, theirs)
    assert [r["noise_seed"] for r in theirs.records] == [None] * 4  # no seed names the noise
    # Without lengths each motion draws its length and noise from its own generator alone: swapping the
    # generators swaps the motions.
    a, b = (torch.Generator().manual_seed(s) for s in (5, 6))
    forward = pipe(prompt=PROMPTS[0], num_motions_per_prompt=2, num_inference_steps=2, generator=[a, b])
    a, b = (torch.Generator().manual_seed(s) for s in (5, 6))
    swapped = pipe(prompt=PROMPTS[0], num_motions_per_prompt=2, num_inference_steps=2, generator=[b, a])
    assert forward.lengths == swapped.lengths[::-1]
    np.testing.assert_allclose(forward.features[0], swapped.features[1], rtol=0, atol=1e-5)
    with pytest.raises(ValueError, match="3 generators for 4 motions"):
        pipe(prompt=PROMPTS, num_motions_per_prompt=2, generator=[torch.Generator() for _ in range(3)])
    with pytest.raises(TypeError, match="torch.Generator or a list of them"):
        pipe(prompt=PROMPTS, generator=[0, 1])


# ---------------------------------------------------------------------------------------------------------------
# .to(), torch_dtype=


def test_to_moves_the_model_and_changes_its_dtype(pipe, exported):
    reference = pipe(prompt=PROMPTS, lengths=20, seed=2, num_inference_steps=2)
    assert pipe.to("cpu") is pipe and pipe.device == torch.device("cpu")
    assert next(pipe.trained.model.parameters()).device == torch.device("cpu")
    pipe.to(torch.bfloat16)
    assert pipe.dtype == torch.bfloat16 and next(pipe.trained.model.parameters()).dtype == torch.bfloat16
    narrow = pipe(prompt=PROMPTS, lengths=20, seed=2, num_inference_steps=2)
    assert narrow.features[0].dtype == np.float32 and narrow.lengths == reference.lengths
    assert not np.array_equal(narrow.features[0], reference.features[0])  # it did run in bfloat16 ...
    scale = max(np.abs(f).max() for f in reference.features)
    assert_same_motions(reference, narrow, atol=0.1 * scale)  # ... and made the same motions up to its rounding
    pipe.to(device="cpu", dtype="float32")
    assert pipe.dtype == torch.float32
    assert_same_motions(reference, pipe(prompt=PROMPTS, lengths=20, seed=2, num_inference_steps=2), atol=1e-2 * scale)
    loaded = MotionPipeline.from_pretrained(exported, device="cpu", torch_dtype=torch.float16)
    assert loaded.dtype == torch.float16
    half = loaded(prompt=PROMPTS, lengths=20, seed=2, num_inference_steps=2)
    assert_same_motions(reference, half, atol=0.1 * scale)
    with pytest.raises(ValueError, match="torch_dtype torch.float64"):
        pipe.to(torch.float64)
    with pytest.raises(ValueError, match="torch_dtype"):
        pipe.to(torch.int64)
    with pytest.raises(SamplingError, match="not a device"):
        pipe.to("tpu")


# ---------------------------------------------------------------------------------------------------------------
# save_pretrained and the exported folder


def test_save_pretrained_writes_a_folder_that_loads_back_and_samples(pipe, exported, text_run, tmp_path):  # noqa: F811
    saved = pipe.save_pretrained(tmp_path / "copy")
    assert {p.name for p in saved.iterdir()} == {p.name for p in exported.iterdir()}
    assert (saved / "README.md").read_text() == (exported / "README.md").read_text()  # the provenance carried over
    again = MotionPipeline.from_pretrained(saved, device="cpu")
    request = {"prompt": PROMPTS, "lengths": [20, 24], "seed": 4, "num_inference_steps": 2}
    assert_same_motions(pipe(**request), again(**request))
    # launch/sample.py takes it as it takes an export
    cli = sample(saved, tmp_path / "cli", "--text", PROMPTS[0], "--length", "20", "--seed", "4", "--steps", "2",
                 "--no-video", "--no-bvh")
    np.testing.assert_allclose(np.load(tmp_path / "cli" / file_of(cli["samples"][0], "features")),
                               again(**request).features[0], rtol=0, atol=1e-5)
    # a pipeline loaded from the checkpoint itself saves what launch/export.py writes
    from_run = MotionPipeline.from_pretrained(text_run, device="cpu").save_pretrained(tmp_path / "from-run")
    assert (from_run / "README.md").read_text() == (exported / "README.md").read_text()
    with pytest.raises(ValueError, match="not an empty folder"):
        pipe.save_pretrained(saved)


def test_exported_files_are_written_with_the_umasks_permissions(text_run, tmp_path):  # noqa: F811
    previous = os.umask(0o022)
    try:
        out = export_pretrained(text_run, tmp_path / "model")
        copy = MotionPipeline.from_pretrained(out, device="cpu").save_pretrained(tmp_path / "copy")
    finally:
        os.umask(previous)
    for folder in (out, copy):
        modes = {p.name: stat.S_IMODE(p.stat().st_mode) for p in folder.iterdir()}
        assert modes == dict.fromkeys(modes, 0o644), modes  # not safetensors' 0600
        assert len(modes) == 4


def test_the_model_card_is_a_hub_card_without_local_paths(exported, text_run, tmp_path_factory):  # noqa: F811
    card = (exported / "README.md").read_text()
    metadata, body = card_metadata(card)
    assert metadata["license"] == "mit"  # LICENSE: MIT
    assert metadata["library_name"] == "motion-flow-matching"
    assert {"text-to-motion", "motion-generation", "flow-matching"} <= set(metadata["tags"])
    assert metadata["datasets"] == ["synthetic"] and metadata["metrics"] == []  # no evaluator results yet
    for section in ("## Use", "## Intended use and limitations", "## Training data", "## Training recipe",
                    "## Evaluation"):
        assert section in body
    manifest = json.loads((text_run.parent / "trainer-dataset" / "manifest.json").read_text())
    for split, facts in manifest["splits"].items():  # the split sizes of the manifest the checkpoint records
        assert f"| {split} | {facts['num_motions']} | {facts['num_captions']} | {facts['num_frames']} |" in body
    assert "- 4 steps, batch" in body and "No evaluator results" in body
    assert "trained with a critic" not in body  # train.critic_weight 0 (tests/test_critic.py: a run with one)
    assert_no_local_path(card, [text_run, exported, tmp_path_factory.getbasetemp()])


def test_the_card_lists_the_evaluators_rows_naming_evaluator_and_protocol(text_run, tmp_path):  # noqa: F811
    run = shutil.copytree(text_run, tmp_path / "run")
    checkpoint = resolve_checkpoint(run)
    marker = ckpt.read_marker(checkpoint)
    (run / "eval").mkdir()
    rows = []
    # contrastive/fast twice: a re-evaluation under changed settings appends a row; the card shows the last
    for evaluator, protocol, fid in (("contrastive", "fast", 0.75), ("contrastive", "fast", 0.25), ("t2m", "mdm", 1.5)):
        rows += table_rows(evaluator_result(checkpoint, ckpt.checkpoint_id(marker), evaluator, protocol, fid))
    other = evaluator_result(checkpoint, "another-checkpoint", "t2m", "full", 9.0)
    rows += table_rows(other)  # another checkpoint's: not this card's
    (run / "eval" / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))

    out = export_pretrained(run, tmp_path / "model")
    card = (out / "README.md").read_text()
    metadata, body = card_metadata(card)
    assert metadata["metrics"] == ["fid", "r_precision_top1"]
    table = [line for line in body.splitlines() if line.startswith("| ") and "test, " in line]
    assert len(table) == 4  # per evaluator and protocol: its generated row, then its ground-truth row
    assert table[0].startswith("| contrastive | fast (ours loop) | test, 40 × 3 | euler, 10, 2.5 | generated | 0.25")
    assert table[1].startswith("| contrastive | fast (ours loop) | test, 40 × 3 | — | ground_truth | 0 |")
    assert table[2].startswith("| t2m | mdm (mdm loop) | test, 40 × 3 | euler, 10, 2.5 | generated | 1.5")
    assert table[3].startswith("| t2m | mdm (mdm loop) | test, 40 × 3 | — | ground_truth |")
    assert "official T2M evaluator" in body and "contrastive text-motion evaluator" in body
    assert "protocol `mdm`: MDM's evaluation loop" in body and "protocol `fast`" in body
    assert "0.75" not in body and "protocol `full`" not in body
    assert_no_local_path(card, [run, tmp_path])
    # the rows travel in config.json, so a folder saved again lists them too
    copy = MotionPipeline.from_pretrained(out, device="cpu").save_pretrained(tmp_path / "copy")
    assert (copy / "README.md").read_text() == card


def evaluator_result(checkpoint: Path, checkpoint_id: str, evaluator: str, protocol: str, fid: float) -> dict:
    """A result as pipeline/evaluation/job.py records it (the fields table_rows reads)."""
    metrics = {"fid": {"mean": fid, "ci": 0.01}, "r_precision_top1": {"mean": 0.5, "ci": None}}
    return {
        "key": f"{evaluator}-{protocol}-{checkpoint_id[:8]}-{fid}", "task": "text_to_motion",
        "checkpoint": {"path": str(checkpoint), "name": checkpoint.name, "step": 4, "id": checkpoint_id,
                       "dataset_id": "d"},
        "evaluator": {"kind": evaluator, "id": f"{evaluator}-id"},
        "data": {"dataset_id": "d", "split": "test"},
        "protocol": {"name": protocol, "loop": "mdm" if protocol == "mdm" else "ours", "replications": 3,
                     "num_items": 40, "redraw_items": True},
        "sampling": {"solver": "euler", "steps": 10, "guidance": 2.5},
        "nfe": 10, "model_passes_per_motion": 20, "generation_seconds_per_motion": 0.1, "world_size": 1,
        "created": "2026-01-01T00:00:00Z", "metrics": metrics, "editing": {},
        "ground_truth": {"fid": {"mean": 0.0, "ci": None}},
    }


def assert_no_local_path(text: str, folders: list[Path]) -> None:
    for folder in folders:
        assert str(folder) not in text and str(Path(folder).resolve()) not in text
    assert str(Path.home()) not in text
    absolute = re.findall(r"(?:^|[\s`'\"(])(/[\w.-]+/[\w./-]*)", text)
    assert not absolute, absolute
