"""The ``mdm`` evaluation protocol (configs/eval_mdm.yaml, ``launch/evaluate.py --protocol mdm``): the MDM/MFM
reference loop rule by rule, each rule an option of ProtocolConfig whose default is our loop (docs/protocol.md cites
the reference for each).

Data: the synthetic source with MiniLM captions shared with tests/test_evaluation.py (test split of 10), a tiny
model trained for one step, an untrained (seeded) contrastive evaluator; the T2M evaluator's rules on small tensors
with its published networks at PyTorch's initialisation.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from eval_worker import (
    SMALL_PROTOCOL,
    build_synthetic_dataset,
    random_contrastive_evaluator,
    train_tiny_model,
)

from mfm import metrics
from mfm.evaluators import T2MEvaluator, WordVectorizer
from mfm.evaluators.t2m import caption_length
from pipeline.config import ConfigError
from pipeline.evaluation.config import (
    MDM_RULES,
    OUR_RULES,
    SAMPLING_POINTS,
    SamplingPoint,
    load_eval_config,
    sweep_overrides,
)
from pipeline.evaluation.job import protocol_key
from pipeline.evaluation.replications import _TAG, generate, plan_protocol, rng_of
from pipeline.evaluation.spaces import read_ground_truth_pool
from pipeline.evaluation.store import ResultsStore

pytestmark = pytest.mark.usefixtures("single_thread")


@pytest.fixture(scope="module")
def manifest(tmp_path_factory) -> Path:
    return build_synthetic_dataset(tmp_path_factory.getbasetemp() / "eval-synthetic")


@pytest.fixture(scope="module")
def checkpoint(manifest, tmp_path_factory) -> Path:
    return train_tiny_model(manifest, tmp_path_factory.mktemp("mdm-run"), steps=1) / "checkpoints" / "step-00000001"


@pytest.fixture(scope="module")
def evaluator(manifest, tmp_path_factory) -> Path:
    return random_contrastive_evaluator(manifest, tmp_path_factory.mktemp("mdm-ev") / "contrastive.safetensors")


def _context(protocol: str, checkpoint: Path, evaluator: Path, out: Path, *overrides: str):
    """An evaluation job's scorer and the checkpoint's context under ``protocol`` made small (one process)."""
    from pipeline.distributed import Dist
    from pipeline.evaluation.job import EvaluationJob
    from pipeline.evaluation.replications import PhaseTimer

    cfg = load_eval_config(protocol, overrides=[*SMALL_PROTOCOL, "protocol.sampling_point=sweep",
                                                "sampling.steps=[1]", "tasks.editing=[]",
                                                "tasks.flame=false", f"evaluator.path={evaluator}",
                                                f"output.dir={out}", *overrides])
    dist = Dist(mixed_precision="no", cpu=True)
    job = EvaluationJob(cfg, dist)
    ctx = job.scorer.context(checkpoint, job.store_for(checkpoint).cache_dir, PhaseTimer(dist.device))
    return job, dist, ctx


def _items(gt) -> tuple:
    return gt.key, gt.caption_index.tolist(), gt.offsets.tolist(), gt.lengths.tolist()


# ---------------------------------------------------------------------------------------------------------------
# settings


def test_the_mdm_preset_is_the_reference_loop_rule_by_rule():
    mdm, full = load_eval_config("mdm"), load_eval_config("full")
    p = mdm.protocol
    assert (p.name, p.loop, p.rules()) == ("mdm", "mdm", MDM_RULES)
    assert (p.replications, p.num_samples, p.r_precision_batch, p.diversity_times) == (20, 1000, 32, 300)
    assert (p.mm_num_texts, p.mm_repeats, p.mm_times, p.max_length, p.unit_length) == (100, 30, 10, 196, 4)
    assert (full.protocol.loop, full.protocol.rules()) == ("ours", OUR_RULES)
    assert load_eval_config("fast").protocol.loop == "ours"
    assert load_eval_config("mdm", overrides=["protocol.generated_padding=zero"]).protocol.loop == "mixed"
    # The HumanML3D test set as the T2M loader builds it: 4,384 items.
    reference = plan_protocol(mdm, num_items=4384, mm_candidates=4384)
    assert (reference.num_samples, reference.mm_num_texts, reference.mm_replications) == (1024, 128, 5)
    assert reference.gt_row_items == 4384 and reference.independent_gt and reference.loop == "mdm"
    assert plan_protocol(mdm, num_items=4400, mm_candidates=4400).gt_row_items == 4384  # drop_last: whole batches
    ours = plan_protocol(full, num_items=4384, mm_candidates=4384)
    assert (ours.num_samples, ours.mm_num_texts, ours.mm_replications, ours.gt_row_items) == (4384, 100, 20, 0)
    with pytest.raises(ConfigError, match="redraw_items"):  # independent passes re-draw by definition
        load_eval_config("mdm", overrides=["protocol.redraw_items=false"])
    with pytest.raises(ConfigError, match="generated_padding"):
        load_eval_config("mdm", overrides=["protocol.generated_padding=nan"])
    with pytest.raises(ConfigError, match="mm_replications"):
        load_eval_config("mdm", overrides=["protocol.mm_replications=-1"])
    # Our protocols' unit keys are what they were before the rules existed; the mdm protocol's hash its rules.
    assert not set(MDM_RULES) & set(protocol_key(full.protocol))
    assert set(MDM_RULES) <= set(protocol_key(mdm.protocol))


def test_mfm_sampling_points_are_named_settings_of_the_mdm_protocol():
    """protocol.sampling_point: 'paper' (the mdm preset: MFM's paper evaluates at 10 Euler steps), 'released' (its
    evaluation commands: step_size 0.01 = 100 steps for HumanML3D, 0.02 = 50 for KIT), 'sweep' (ours: the sampling
    lists). A named point is the only one; a sweep given beside it is refused, not ignored."""
    mdm = load_eval_config("mdm")
    assert mdm.protocol.sampling_point == "paper"
    assert mdm.sampling_points("humanml3d") == mdm.sampling_points("kit") == [SamplingPoint("euler", 10, 2.5)]
    released = load_eval_config("mdm", overrides=["protocol.sampling_point=released"])
    assert released.sampling_points("humanml3d") == [SamplingPoint("euler", 100, 2.5)]
    assert released.sampling_points("kit") == [SamplingPoint("euler", 50, 2.5)]
    assert SAMPLING_POINTS["released"]["humanml3d"].name == "euler-100steps-g2.5"
    with pytest.raises(ConfigError, match="no sampling point for skeleton 'smpl'"):
        released.sampling_points("smpl")
    for flags in (sweep_overrides(None, "50", None), sweep_overrides("midpoint", None, None),
                  sweep_overrides(None, None, "3.0"), ["sampling.steps_per_solver={euler: [5]}"]):
        with pytest.raises(ConfigError, match="protocol.sampling_point=paper fixes the sampling point"):
            load_eval_config("mdm", overrides=flags)
    swept = load_eval_config("mdm", overrides=["protocol.sampling_point=sweep", *sweep_overrides(None, "5,50", None)])
    assert [p.name for p in swept.sampling_points("kit")] == ["euler-5steps-g2.5", "euler-50steps-g2.5"]
    full = load_eval_config("full")  # ours: the sweep, whose key is what it was before the setting existed
    assert full.protocol.sampling_point == "sweep" and full.sampling_points("humanml3d") == full.sampling.points()
    assert "sampling_point" not in protocol_key(full.protocol)
    assert protocol_key(mdm.protocol)["sampling_point"] == "paper"
    assert protocol_key(released.protocol) != protocol_key(mdm.protocol)
    with pytest.raises(ConfigError, match="sampling_point"):
        load_eval_config("mdm", overrides=["protocol.sampling_point=fast"])


# ---------------------------------------------------------------------------------------------------------------
# test items and the ground-truth row


def test_items_are_redrawn_per_replication_and_pass_and_the_same_for_the_same_seed(manifest):
    """Both protocols: replication r's items from (seed, r) (our loop: one draw; mdm: passes 0, 1, 2 of the
    reference's loaders), different in every replication and pass, the same whoever draws them with that seed."""
    pool = read_ground_truth_pool(manifest, "test", seed=0)
    draws = {(r, s): pool.draw(r, s) for r in range(3) for s in range(3)}
    assert len({d.key for d in draws.values()}) == 9 and all(d.ids == pool.draw(None).ids for d in draws.values())
    assert len({tuple(map(str, _items(d)[1:])) for d in draws.values()}) == 9  # captions / crops differ
    assert all(_items(draws[r, 0]) == _items(pool.draw(r)) for r in range(3))  # our loop's set is pass 0
    again = read_ground_truth_pool(manifest, "test", seed=0)
    assert all(_items(again.draw(r, s)) == _items(d) for (r, s), d in draws.items())
    other = read_ground_truth_pool(manifest, "test", seed=1)
    assert all(_items(other.draw(r, s))[1:] != _items(d)[1:] for (r, s), d in draws.items())
    with pytest.raises(ValueError, match="stream"):
        pool.draw(None, 1)


def test_ground_truth_fid_under_mdm_is_that_of_two_independent_draws(checkpoint, evaluator, tmp_path):
    """Default: the GT row's FID is a bootstrap resample of the replication's draw against it (as before). mdm: the
    GT row is a pass of its own, scored against FID statistics from another pass: non-zero, and it changes with the
    seed; each replication draws other passes, the same ones when the context is built again."""
    from pipeline.evaluation.replications import PhaseTimer

    results, contexts = {}, {}
    for name, protocol, seed in (("ours", "fast", 0), ("mdm", "mdm", 0), ("mdm-seed1", "mdm", 1), ("again", "mdm", 0)):
        job, dist, ctx = _context(protocol, checkpoint, evaluator, tmp_path / name, f"protocol.seed={seed}")
        contexts[name] = (ctx, dist)
        if name != "again":
            results[name] = job.scorer.evaluate_point(ctx, ctx.points[0], PhaseTimer(dist.device))
    ctx, dist = contexts["ours"]
    for r, value in enumerate(results["ours"]["ground_truth"]["fid"]["values"]):
        emb = ctx.truth(r, dist).emb.motion
        boot = rng_of(0, _TAG["bootstrap"], r).integers(0, len(emb), len(emb))
        assert value == pytest.approx(metrics.fid(emb[boot], emb), rel=1e-9)
    assert ctx.passes(0, dist, 0) is None
    ctx, dist = contexts["mdm"]
    twin, twin_dist = contexts["again"]
    values = results["mdm"]["ground_truth"]["fid"]["values"]
    for r, value in enumerate(values):
        own, passes = ctx.truth(r, dist).gt, ctx.passes(r, dist, 0)
        assert len({own.key, passes.row.gt.key, passes.stats.gt.key}) == 3
        assert value == pytest.approx(metrics.fid(passes.row.emb.motion[passes.row_items],
                                                  passes.stats.emb.motion[passes.stats_items]), rel=1e-9)
        assert value > 1e-6
        again = twin.passes(r, twin_dist, 0)
        assert (_items(again.row.gt), _items(again.stats.gt)) == (_items(passes.row.gt), _items(passes.stats.gt))
    first, second = ctx.passes(0, dist, 0), ctx.passes(1, dist, 0)
    assert _items(first.row.gt)[1:] != _items(second.row.gt)[1:] and first.stats.gt.key != second.stats.gt.key
    assert results["mdm-seed1"]["ground_truth"]["fid"]["values"] != pytest.approx(values)
    sets = results["mdm"]["ground_truth_sets"]
    assert [s["replication"] for s in sets] == [0, 1] and all({"row_gt_key", "stats_gt_key"} <= set(s) for s in sets)


def test_generated_and_multimodality_motions_reach_the_evaluator_as_the_rules_say(checkpoint, evaluator, tmp_path):
    """Ours: every generated motion zero past its length, in the evaluator's normalisation. mdm: the main and
    MultiModality motions with what the sampler left past the length; MultiModality ones in the model's
    normalisation (the evaluator's own skipped); edits as ours."""
    from pipeline.evaluation.replications import PhaseTimer, PointRun

    class Recorder:
        def __init__(self):
            self.calls = []

        def encode_motions(self, features, lengths, *, keep_padding=False, normalized=False):
            self.calls.append((features, keep_padding, normalized))
            return torch.zeros(len(features), 4)

    raw, lengths = torch.randn(2, 196, 263) * 3 + 1, torch.tensor([40, 60])
    for protocol in ("fast", "mdm"):
        job, dist, ctx = _context(protocol, checkpoint, evaluator, tmp_path / protocol)
        run = PointRun(job.cfg, dist, ctx, ctx.points[0], PhaseTimer(dist.device))
        assert run.window == (196 if protocol == "mdm" else None)
        run.space = recorder = Recorder()
        for kind in ("main", "mm", "edit:prediction"):
            run.encode_generated(kind, raw, lengths)
        seen = [(keep, normalized) for _, keep, normalized in recorder.calls]
        if protocol == "fast":
            assert seen == [(False, False)] * 3 and all(f is raw for f, *_ in recorder.calls)
        else:
            assert seen == [(True, False), (True, True), (False, False)]
            torch.testing.assert_close(recorder.calls[1][0], ctx.trained.normalize(raw))


# ---------------------------------------------------------------------------------------------------------------
# what the T2M evaluator reads: frames past the length, caption lengths


VOCAB = ["sos", "eos", "unk", "a", "man", "walk", "forward", "slowly"]


def _t2m_evaluator() -> tuple[T2MEvaluator, np.ndarray, np.ndarray]:
    """The published networks at PyTorch's initialisation, a small vocabulary and a random normalisation."""
    rng = np.random.default_rng(0)
    torch.manual_seed(0)
    vectorizer = WordVectorizer(rng.standard_normal((len(VOCAB), 300)), VOCAB, {w: i for i, w in enumerate(VOCAB)})
    mean, std = rng.standard_normal(263) * 0.1, rng.uniform(0.5, 1.5, 263)
    return T2MEvaluator("t2m", vectorizer, mean, std), mean, std


def test_padding_rule_what_the_evaluator_sees_past_the_length(checkpoint):
    """Ours: zero past each length (the evaluator's normalisation), whatever the motion holds there. mdm: the
    motion's own frames past the length, normalised like the others (zero only beyond what it gives); the sampler
    then fills a 196-frame window, noise on every frame, instead of zeros past the length."""
    evaluator, mean, std = _t2m_evaluator()
    lengths = torch.tensor([40, 100])
    raw = torch.from_numpy(np.random.default_rng(1).standard_normal((2, 120, 263))).float()
    ours = evaluator.normalized_window(raw, lengths)
    kept = evaluator.normalized_window(raw, lengths, keep_padding=True)
    normalised = ((raw.double() - torch.from_numpy(mean)) / torch.from_numpy(std)).float()
    assert ours.shape == kept.shape == (2, 196, 263)
    for row, n in enumerate(lengths.tolist()):
        torch.testing.assert_close(ours[row, :n], normalised[row, :n])
        torch.testing.assert_close(kept[row, :n], normalised[row, :n])
        assert torch.all(ours[row, n:] == 0)
        torch.testing.assert_close(kept[row, n:120], normalised[row, n:])
        assert torch.all(kept[row, 120:] == 0)
    torch.testing.assert_close(evaluator.normalized_window(normalised, lengths, keep_padding=True, normalized=True),
                               kept)
    # The movement encoder convolves across the length: only the mdm rule lets the padding reach the embedding.
    other = raw.clone()
    other[0, 40:] += 5.0
    assert torch.allclose(evaluator.encode_motions(other, lengths), evaluator.encode_motions(raw, lengths))
    changed = evaluator.encode_motions(other, lengths, keep_padding=True)
    assert not torch.allclose(changed[0], evaluator.encode_motions(raw, lengths, keep_padding=True)[0])

    from pipeline.generation.inference import load_trained_model

    trained = load_trained_model(checkpoint, use_ema=True, device="cpu")
    sampling = load_eval_config("mdm").sampling
    lengths = torch.tensor([24, 36])
    cond = torch.from_numpy(np.random.default_rng(2).standard_normal((2, trained.model_config.cond_dim))).float()
    point = SamplingPoint("euler", 2, 2.5)
    zeroed, _ = generate(trained, cond, {}, lengths, [1, 2], point, sampling)
    window, _ = generate(trained, cond, {}, lengths, [1, 2], point, sampling, window=196)
    assert zeroed.shape[1] == 36 and window.shape[1] == 196
    padding = trained.normalize(window)[0, 24:]  # our model masks padding: its initial noise stays there
    assert torch.all(zeroed[0, 24:] == 0) and 0.8 < float(padding.std()) < 1.2


def test_caption_length_rule_on_a_hand_made_caption():
    """The reference's ground truth: sos + words + eos; its generated row: the length of the unk-padded token list
    it re-split on '_' (22), whatever the caption."""
    caption = ["a/DET", "man/NOUN", "walk/VERB", "forward/ADV"]
    padded_list = ["sos/OTHER", *caption, "eos/OTHER"] + ["unk/OTHER"] * 16  # dataset.py: 350-354
    assert caption_length(caption) == 6 and caption_length(caption, "padded") == len(
        "_".join(padded_list).split("_")) == 22
    long = ["man/NOUN", "walk/VERB"] * 13  # 26 tokens: cropped to 20, so both rules give 22
    assert caption_length(long) == caption_length(long, "padded") == 22
    evaluator, _, _ = _t2m_evaluator()
    words, pos, lens = evaluator.vectorizer.encode_batch([caption, ["slowly/ADV"]], "padded")
    words_s, pos_s, lens_s = evaluator.vectorizer.encode_batch([caption, ["slowly/ADV"]])
    assert lens.tolist() == [22, 22] and lens_s.tolist() == [6, 3]
    assert torch.equal(words, words_s) and torch.equal(pos, pos_s)  # the same 22 word vectors, another length
    padded = evaluator.encode_texts([caption], "padded")
    torch.testing.assert_close(padded, evaluator.encode_word_features(words[:1], pos[:1], torch.tensor([22])))
    assert not torch.allclose(padded, evaluator.encode_texts([caption]))
    with pytest.raises(ValueError, match="caption length rule"):
        caption_length(caption, "reference")


# ---------------------------------------------------------------------------------------------------------------
# results


def test_results_record_the_protocol_its_loop_and_rules(checkpoint, evaluator, tmp_path, monkeypatch):
    """results.json and the table name the protocol and the loop it ran; mdm's rules are all recorded. The
    generated row's retrieval reads the captions embedded with the padded length, the GT row the sentence one."""
    import pipeline.evaluation.replications as replications
    from launch.evaluate import main
    from pipeline.evaluation.spaces import ContrastiveSpace

    encode_texts = ContrastiveSpace.encode_texts

    def marked(self, gt, indices, lengths="sentence"):  # the contrastive evaluator reads no length: mark one
        out = encode_texts(self, gt, indices, lengths)
        return out + 100.0 if lengths == "padded" else out  # unit-norm embeddings: the mark stands out

    seen = []
    retrieval = replications.retrieval_metrics

    def recording(text, motion, *args):
        seen.append(text.copy())
        return retrieval(text, motion, *args)

    monkeypatch.setattr(ContrastiveSpace, "encode_texts", marked)
    monkeypatch.setattr(replications, "retrieval_metrics", recording)
    results = {}
    for protocol in ("mdm", "fast"):
        out = tmp_path / protocol
        seen.clear()
        # mdm at its named point (the paper's 10 Euler steps), fast at the sweep's 1 step
        steps = [] if protocol == "mdm" else ["sampling.steps=[1]"]
        assert main(["--checkpoint", str(checkpoint), "--protocol", protocol, *SMALL_PROTOCOL, *steps,
                     "tasks.editing=[]", "tasks.flame=false", f"evaluator.path={evaluator}",
                     f"output.dir={out}"]) == 0
        (path,) = (out / "results").rglob("*.json")
        results[protocol] = result = json.loads(path.read_text())
        rows = ResultsStore(out).table_rows()
        assert [(r["protocol"], r["protocol_loop"]) for r in rows] == [(protocol, result["protocol"]["loop"])] * 2
        named = "paper" if protocol == "mdm" else "sweep"
        assert [(r["sampling_point"], r["steps"]) for r in rows] == [(named, 10 if named == "paper" else 1)] * 2
        assert result["sampling"]["sampling_point"] == result["protocol"]["config"]["sampling_point"] == named
        generated, truth = seen[0::2], seen[1::2]  # per replication: the generated row, then the GT row
        assert len(generated) == 2 and all((g > 50).all() == (protocol == "mdm") for g in generated)
        assert len(truth) == 2 and all((np.abs(t) <= 1).all() for t in truth)
    assert "10 Euler steps" in results["mdm"]["sampling"]["sampling_point_source"]
    assert "sampling_point_source" not in results["fast"]["sampling"]
    mdm, fast = results["mdm"]["protocol"], results["fast"]["protocol"]
    assert (mdm["name"], mdm["loop"], mdm["rules"]) == ("mdm", "mdm", MDM_RULES)
    assert {k: mdm["config"][k] for k in MDM_RULES} == MDM_RULES and mdm["mm_replications"] == 2
    assert (fast["name"], fast["loop"], fast["rules"]) == ("fast", "ours", OUR_RULES)
    assert "three independent passes" in mdm["intervals"] and "three" not in fast["intervals"]
    assert any("generated_caption_length=padded has no effect" in n for n in results["mdm"]["notes"])
    assert results["mdm"]["key"] != results["fast"]["key"]
    for result in results.values():  # the five T2M metrics with intervals over the replications
        for name in ("fid", "r_precision_top3", "mm_dist", "diversity", "multimodality"):
            assert len(result["metrics"][name]["values"]) == 2 and np.isfinite(result["metrics"][name]["mean"])
