import dataclasses
import json

import pytest

from mfm.model import ModelConfig
from pipeline.config import (
    CONFIG_DIR,
    ConfigError,
    DataConfig,
    OptimConfig,
    TrainConfig,
    TrainLoopConfig,
    available_presets,
    from_dict,
    load_config,
    parse_override,
    to_dict,
    to_yaml,
)

PRESETS = ["default", "humanml3d", "humanml3d_mfm", "kit", "synthetic", "tiny"]


def test_all_expected_presets_exist():
    assert set(PRESETS) <= set(available_presets())


@pytest.mark.parametrize("preset", PRESETS)
def test_preset_loads_and_round_trips(preset, tmp_path):
    cfg = load_config(TrainConfig, preset)
    assert isinstance(cfg.model, ModelConfig)  # the model section is mfm.model's own dataclass
    plain = to_dict(cfg)
    json.dumps(plain)  # what checkpoints store must be plain data
    assert from_dict(TrainConfig, plain) == cfg
    saved = tmp_path / "resolved.yaml"
    saved.write_text(to_yaml(cfg))
    assert load_config(TrainConfig, saved) == cfg


def test_paper_presets_match_mfm():
    hml = load_config(TrainConfig, "humanml3d")
    assert (hml.model.feature_dim, hml.model.latent_dim, hml.model.ff_dim) == (263, 512, 1024)
    assert (hml.model.num_layers, hml.model.num_heads, hml.model.dropout) == (8, 4, 0.1)
    assert (hml.data.window, hml.data.batch_size, hml.optim.lr, hml.train.max_steps) == (196, 128, 1e-4, 600_000)
    assert (hml.model.prediction, hml.model.cond_scaling) == ("data", "rms")  # ours: docs/generator-study.md
    # ours (configs/humanml3d.yaml's header, docs/generator-study.md): the loss's weight cap and the sampler defaults
    assert (hml.train.flow_velocity_weight_cap, hml.model.guided_features, hml.model.output_smoothing) == (9, "pose", 0)
    mfm = load_config(TrainConfig, "humanml3d_mfm")  # MFM's recipe exactly
    assert (mfm.model.prediction, mfm.model.cond_scaling) == ("velocity", "none")
    assert (mfm.train.flow_velocity_weight_cap, mfm.model.guided_features, mfm.model.output_smoothing) == (0, "all", 0)
    assert dataclasses.replace(mfm.model, prediction="data", cond_scaling="rms", guided_features="pose") == hml.model
    assert (mfm.data, mfm.optim) == (hml.data, hml.optim)
    assert dataclasses.replace(mfm.train, flow_velocity_weight_cap=9.0, out_dir=hml.train.out_dir) == hml.train
    kit = load_config(TrainConfig, "kit")
    assert (kit.model.feature_dim, kit.train.max_steps) == (251, 300_000)
    # KIT is the HumanML3D recipe on 251-D features: every other setting as humanml3d (its file once left out
    # prediction and cond_scaling and trained MFM's parametrisation while its header said otherwise)
    assert dataclasses.replace(kit.model, feature_dim=263) == hml.model
    assert kit.optim == hml.optim
    assert dataclasses.replace(kit.train, max_steps=hml.train.max_steps, out_dir=hml.train.out_dir) == hml.train
    tiny = load_config(TrainConfig, "tiny")
    assert (tiny.model.num_layers, tiny.model.latent_dim, tiny.train.mixed_precision) == (2, 64, "no")


def test_overrides_beat_preset_and_are_typed():
    cfg = load_config(
        TrainConfig,
        "tiny",
        [
            "optim.lr=3e-4",  # PyYAML's 1.1 rules would read this as a string
            "optim.betas=[0.8, 0.95]",
            "train.max_steps=6e2",  # integral float accepted for an int
            "data.verify=off",  # YAML 1.1 would make this False
            "model.length_token=true",
            "train.out_dir=/tmp/run one",
            "model.num_layers=3",
        ],
    )
    assert cfg.optim.lr == 3e-4 and isinstance(cfg.optim.lr, float)
    assert cfg.optim.betas == (0.8, 0.95)
    assert cfg.train.max_steps == 600 and isinstance(cfg.train.max_steps, int)
    assert cfg.data.verify == "off"
    assert cfg.model.length_token is True
    assert cfg.train.out_dir == "/tmp/run one"
    assert cfg.model.num_layers == 3
    # untouched preset values survive, untouched defaults too
    assert cfg.model.latent_dim == 64
    assert cfg.optim.grad_accum == OptimConfig().grad_accum


def test_later_override_wins():
    cfg = load_config(TrainConfig, None, ["optim.lr=0.1", "optim.lr=0.2"])
    assert cfg.optim.lr == 0.2


def test_no_preset_gives_defaults():
    assert load_config(TrainConfig) == TrainConfig()


@pytest.mark.parametrize(
    ("override", "fragments"),
    [
        ("model.num_layer=2", ["model.num_layer", "num_layers", "latent_dim"]),
        ("foo=1", ["'foo'", "data", "model", "optim", "train"]),
        ("optim.lr.x=1", ["optim.lr", "not a section"]),
    ],
)
def test_unknown_override_key_names_key_and_valid_keys(override, fragments):
    with pytest.raises(ConfigError) as info:
        load_config(TrainConfig, "tiny", [override])
    for fragment in fragments:
        assert fragment in str(info.value)


@pytest.mark.parametrize(
    ("override", "fragment"),
    [
        ("model.num_layers=true", "model.num_layers: expected int"),
        ("model.num_layers=2.5", "model.num_layers: expected int"),
        ("optim.lr=fast", "optim.lr: expected float"),
        ("data.verify=maybe", "data.verify: expected one of"),
        ("optim.betas=[0.9]", "optim.betas: expected 2 items"),
        ("train.out_dir=", "train.out_dir: expected str, got NoneType"),
        ("data={window: 8, colour: red}", "data.colour"),
        ("model.num_heads=3", "divisible by num_heads"),  # mfm.model.ModelConfig's own validation
        ("optim.ema_decay=1.0", "optim.ema_decay"),
        ("optim.ema_start=-1", "optim.ema_start must be >= 0"),
        ("train.flow_feat_bias=0", "train.flow_feat_bias must be > 0"),
        ("train.flow_trajectory_weight=-1", "train.flow_trajectory_weight must be >= 0"),
        ("train.flow_root_mean_weight=-1", "train.flow_root_mean_weight must be >= 0"),
        ("train.flow_input_perturbation=-0.1", "train.flow_input_perturbation must be >= 0"),
        ("train.flow_foot_contact_weight=-1", "train.flow_foot_contact_weight must be >= 0"),
        ("train.flow_trajectory_min_t=1", "train.flow_trajectory_min_t must be in [0, 1)"),
        ("train.flow_trajectory_huber=-0.1", "train.flow_trajectory_huber must be >= 0"),
        ("train.flow_bone_target=clip_median", "the bone term, which is off"),
        ("train.flow_bone_target=mean", "train.flow_bone_target"),
        ("train.flow_trajectory_start_step=-1", "train.flow_trajectory_start_step must be in [0, train.max_steps="),
    ],
)
def test_bad_override_values_fail_naming_the_key(override, fragment):
    with pytest.raises(ConfigError) as info:
        load_config(TrainConfig, "tiny", [override])
    assert fragment in str(info.value)


@pytest.mark.parametrize("text", ["nokey", "=3", "optim..lr=1", ".lr=2"])
def test_malformed_override(text):
    with pytest.raises(ConfigError, match="not of the form"):
        parse_override(text)


def test_parse_override_splits_on_first_equals():
    assert parse_override("train.resume=runs/a=b/step-00000010") == (["train", "resume"], "runs/a=b/step-00000010")


def test_unknown_key_in_yaml_file_names_key(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("optim:\n  lr: 1.0e-4\n  warmup: 10\n")
    with pytest.raises(ConfigError) as info:
        load_config(TrainConfig, path)
    assert "optim.warmup" in str(info.value) and "warmup_steps" in str(info.value)


def test_yaml_scalars_follow_yaml_1_2(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("data:\n  verify: off\noptim:\n  lr: 1e-4\ntrain:\n  wandb: online\n  mixed_precision: no\n")
    cfg = load_config(TrainConfig, path)
    assert (cfg.data.verify, cfg.optim.lr, cfg.train.wandb, cfg.train.mixed_precision) == ("off", 1e-4, "online", "no")


def test_invalid_yaml_names_the_file(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("optim: [unclosed\n")
    with pytest.raises(ConfigError, match="broken.yaml"):
        load_config(TrainConfig, path)


def test_top_level_must_be_a_mapping(tmp_path):
    path = tmp_path / "list.yaml"
    path.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(TrainConfig, path)


def test_missing_preset_lists_available():
    with pytest.raises(FileNotFoundError) as info:
        load_config(TrainConfig, "no-such-preset")
    assert "tiny" in str(info.value) and str(CONFIG_DIR) in str(info.value)


def test_missing_preset_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_config(TrainConfig, tmp_path / "absent.yaml")


def test_direct_construction_is_validated_and_coerced():
    assert OptimConfig(betas=[0.5, 0.6]).betas == (0.5, 0.6)
    with pytest.raises(ConfigError, match="window"):
        DataConfig(window="196")
    with pytest.raises(ConfigError, match="batch_size"):
        DataConfig(batch_size=0)
    with pytest.raises(ConfigError, match="keep_last"):
        TrainLoopConfig(keep_last=-1)
    with pytest.raises(ConfigError, match="mixed_precision"):
        TrainLoopConfig(mixed_precision="fp8")
    with pytest.raises(ConfigError, match="flow_velocity_weight_cap must be >= 0"):
        TrainLoopConfig(flow_velocity_weight_cap=-1)
    with pytest.raises(ConfigError, match="applies to train.flow_loss=velocity"):
        TrainLoopConfig(flow_loss="data", flow_velocity_weight_cap=9)
    with pytest.raises(TypeError):  # keyword-only: no positional surprises
        DataConfig("manifest.json")


def test_sections_are_frozen():
    cfg = TrainConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.optim = OptimConfig(lr=1.0)  # type: ignore[misc]
    assert dataclasses.replace(cfg, optim=OptimConfig(lr=1.0)).optim.lr == 1.0


def test_cross_section_checks():
    with pytest.raises(ConfigError, match="max_len"):
        TrainConfig(data=DataConfig(window=300), model=ModelConfig(max_len=200))
    with pytest.raises(ConfigError, match="max_frames"):
        TrainConfig(data=DataConfig(window=250), model=ModelConfig(length_token=True, max_frames=196))
    ok = TrainConfig(data=DataConfig(window=196), model=ModelConfig(length_token=True, max_frames=196))
    assert ok.data.window == 196
    with pytest.raises(ConfigError, match="guided_features"):
        TrainConfig(model=ModelConfig(guided_features="pose"), train=TrainLoopConfig(objective="diffusion"))
    assert TrainConfig(model=ModelConfig(guided_features="pose")).model.guided_features == "pose"


def test_from_dict_rejects_unknown_nested_and_keeps_defaults():
    assert from_dict(TrainConfig, {"train": {"seed": 7}}).train == TrainLoopConfig(seed=7)
    with pytest.raises(ConfigError, match="model.widht"):
        from_dict(TrainConfig, {"model": {"widht": 3}})


def test_compile_auto_compiles_on_cuda_only_and_booleans_still_read():
    """train.compile: auto (every preset) compiles on a CUDA device and not on CPU; true/false as before."""
    import torch

    from pipeline.training.trainer import compiles

    assert [load_config(TrainConfig, "tiny", [f"train.compile={v}"]).train.compile for v in ("auto", "true", "false")] \
        == ["auto", True, False]
    assert all(load_config(TrainConfig, p, []).train.compile == "auto" for p in available_presets() if p != "tiny" and not p.startswith("eval_"))
    assert compiles("auto", torch.device("cuda")) and not compiles("auto", torch.device("cpu"))
    assert compiles(True, torch.device("cpu")) and not compiles(False, torch.device("cuda"))
    with pytest.raises(ConfigError, match="train.compile"):
        load_config(TrainConfig, "tiny", ["train.compile=maybe"])


def test_grid_times_are_for_a_pair_set_only():
    with pytest.raises(ConfigError, match="pair set"):
        TrainLoopConfig(flow_time_sampling="grid")
    assert TrainLoopConfig(flow_time_sampling="grid", flow_noise="recorded").flow_time_grid_steps == 2


def test_own_path_grid_inputs_need_grid_times_and_nothing_that_changes_the_models_own_steps():
    reflow = ["train.flow_time_sampling=grid", "train.flow_noise=recorded", "data.unit_length=1"]
    assert load_config(TrainConfig, "tiny", [*reflow, "train.flow_grid_inputs=own_path"]).train.flow_grid_inputs \
        == "own_path"
    for extra in ([], ["model.self_condition_prob=0.5"], ["train.flow_input_perturbation=0.1"]):
        overrides = (reflow if extra else []) + extra + ["train.flow_grid_inputs=own_path"]
        with pytest.raises(ConfigError, match="flow_grid_inputs=own_path"):
            load_config(TrainConfig, "tiny", overrides)
    with pytest.raises(ConfigError, match="flow_grid_inputs"):
        load_config(TrainConfig, "tiny", [*reflow, "train.flow_grid_inputs=straight"])


def test_sampling_times_are_a_solves_start_times_and_the_grid_trains_exactly_them():
    reflow = ["train.flow_time_sampling=grid", "train.flow_noise=recorded", "data.unit_length=1"]
    cfg = load_config(TrainConfig, "tiny", [*reflow, "model.sampling_times=[0,0.9]"])
    assert cfg.model.sampling_times == (0, 0.9)
    assert load_config(TrainConfig, "tiny", ["model.sampling_times=[0,0.9]"]).train.flow_time_sampling == "uniform"
    for times in ("[0.1,0.9]", "[0,0.9,0.5]", "[0,1]", "[]"):
        with pytest.raises(ConfigError, match="sampling_times"):
            load_config(TrainConfig, "tiny", [f"model.sampling_times={times}"])
    with pytest.raises(ConfigError, match="flow_time_grid_steps must be 3"):
        load_config(TrainConfig, "tiny", [*reflow, "model.sampling_times=[0,0.5,0.9]"])
    with pytest.raises(ConfigError, match="shortcut"):
        load_config(TrainConfig, "tiny", ["model.sampling_times=[0,0.9]", "model.shortcut_levels=2"])
