"""Published MFM (``MDM_Flow``) and MDM checkpoints as :class:`mfm.model.MotionFlowTransformer` weights.

Both reference code bases share MDM's ``trans_enc`` network, saved as a plain state dict with these names (the
published HumanML3D models: width 512, FF 1024, 8 layers; CLIP's weights are removed before saving)::

    input_process.poseEmbedding.{weight,bias}            → input_proj
    embed_timestep.time_embed.{0,2}.{weight,bias}        → time_embedding.mlp.{0,2}
    embed_text.{weight,bias}                             → cond_proj                (text models)
    embed_action.action_embedding                        → action_embedding.weight  (action models)
    seqTransEncoder.layers.N.self_attn.in_proj_{weight,bias}  → layers.N.qkv   (q, k, v stacked, heads contiguous)
    seqTransEncoder.layers.N.self_attn.out_proj.*        → layers.N.out_proj
    seqTransEncoder.layers.N.{linear1,linear2,norm1,norm2}.*  → the same names
    output_process.poseFinal.{weight,bias}               → output_proj
    sequence_pos_encoder.pe (5000, 1, d)                 → positional_table (with positional_table='stored';
                                                          embed_timestep's copy is the same module's buffer)

What the shapes cannot say is taken from the reference code: 4 attention heads (MDM and MFM hard-code
``num_heads=4``), GELU, post-norm layers. The reference's behaviour where it differs from our defaults is
reproduced by :data:`REFERENCE_BEHAVIOUR` (``ModelConfig.time_grid``, ``attend_padding`` and
``positional_table='stored'``: the reference's own table, computed on its device, differs from ours by float32
rounding, up to 3e-5 in the rows a 196-frame model and the time lookup use). The table's layout already agrees:
one sinusoid added to every token, position 0 = the condition token, sin on even and cos on odd channels.
"""

from __future__ import annotations

import pickle
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from mfm.model import ModelConfig, sinusoidal_embedding

REFERENCE_KINDS = ("mfm", "mdm")
"""'mfm': MFM's ``MDM_Flow`` (a velocity field, flow matching); 'mdm': MDM (an x0 denoiser, 1000 cosine steps)."""

REFERENCE_BEHAVIOUR: dict[str, dict[str, Any]] = {
    # MFM looks the time table up at (t·1000).long(): t rounded down to the 1/1000 grid.
    "mfm": {"time_grid": "floor", "attend_padding": True, "positional_table": "stored"},
    # MDM passes integer steps; our diffusion code passes step/1000, which 'nearest' maps back exactly.
    "mdm": {"time_grid": "nearest", "attend_padding": True, "positional_table": "stored"},
}
"""ModelConfig settings that reproduce each reference's forward pass (converted checkpoints default to them)."""
OUR_BEHAVIOUR: dict[str, Any] = {"time_grid": "continuous", "attend_padding": False, "positional_table": "computed"}

DEFAULT_NUM_HEADS = 4
"""MDM and MFM construct ``MDM_Flow``/``MDM`` with ``num_heads=4`` and never expose it; shapes cannot tell."""
DEFAULT_ACTIVATION = "gelu"
DEFAULT_DROPOUT = 0.1  # the reference's training dropout; inactive in eval, kept so fine-tuning starts alike
DEFAULT_COND_DROP_PROB = 0.1  # MDM/MFM's cond_mask_prob for text and action models
DROPPED_PREFIXES = ("clip_model.",)
"""Keys of a reference state dict that are not the motion network (MFM/MDM strip CLIP before saving; a few
re-saved files keep it)."""
POSITIONAL_TABLE_TOLERANCE = 1e-3
"""A stored table must be MDM's sinusoid up to float32 rounding on another device (seen: 2.4e-4 near row 5,000);
anything further is another positional encoding."""

_LAYER_KEY = re.compile(r"^seqTransEncoder\.layers\.(\d+)\.")
_LAYER_PARAMS = {
    "self_attn.in_proj_weight": "qkv.weight",
    "self_attn.in_proj_bias": "qkv.bias",
    "self_attn.out_proj.weight": "out_proj.weight",
    "self_attn.out_proj.bias": "out_proj.bias",
    "linear1.weight": "linear1.weight",
    "linear1.bias": "linear1.bias",
    "linear2.weight": "linear2.weight",
    "linear2.bias": "linear2.bias",
    "norm1.weight": "norm1.weight",
    "norm1.bias": "norm1.bias",
    "norm2.weight": "norm2.weight",
    "norm2.bias": "norm2.bias",
}
_SHARED_PARAMS = {
    "input_process.poseEmbedding.weight": "input_proj.weight",
    "input_process.poseEmbedding.bias": "input_proj.bias",
    "embed_timestep.time_embed.0.weight": "time_embedding.mlp.0.weight",
    "embed_timestep.time_embed.0.bias": "time_embedding.mlp.0.bias",
    "embed_timestep.time_embed.2.weight": "time_embedding.mlp.2.weight",
    "embed_timestep.time_embed.2.bias": "time_embedding.mlp.2.bias",
    "output_process.poseFinal.weight": "output_proj.weight",
    "output_process.poseFinal.bias": "output_proj.bias",
}
_TEXT_PARAMS = {"embed_text.weight": "cond_proj.weight", "embed_text.bias": "cond_proj.bias"}
_ACTION_PARAMS = {"embed_action.action_embedding": "action_embedding.weight"}
_POSITIONAL_TABLES = ("sequence_pos_encoder.pe", "embed_timestep.sequence_pos_encoder.pe")


class ReferenceCheckpointError(ValueError):
    """A reference checkpoint that cannot be read or mapped; the message names the file and the keys."""


def load_reference_state_dict(path: str | Path) -> tuple[dict[str, Tensor], dict[str, str], list[str]]:
    """``(state_dict, metadata, dropped_keys)`` of a reference checkpoint, on CPU, without running pickle code.

    ``.safetensors`` files are read directly (their metadata returned); anything else with
    ``torch.load(weights_only=True)``, which refuses objects that need code to rebuild (an argparse Namespace, a
    whole pickled model): those are refused here with the reason. A ``{'model': state_dict, ...}`` or
    ``{'state_dict': ...}`` wrapper and a DDP ``module.`` prefix are unwrapped; CLIP keys are dropped (listed).
    """
    path = Path(path)
    if not path.is_file():
        raise ReferenceCheckpointError(f"{path}: no such checkpoint file")
    metadata: dict[str, str] = {}
    if path.suffix == ".safetensors":
        from safetensors import SafetensorError, safe_open

        try:
            with safe_open(str(path), framework="pt", device="cpu") as handle:
                metadata = dict(handle.metadata() or {})
                loaded: Any = {key: handle.get_tensor(key) for key in handle.keys()}  # noqa: SIM118 (not a dict)
        except SafetensorError as err:
            raise ReferenceCheckpointError(f"{path}: not a readable safetensors file ({err})") from err
    else:
        try:
            loaded = torch.load(path, map_location="cpu", weights_only=True)
        except pickle.UnpicklingError as err:
            reason = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise ReferenceCheckpointError(
                f"{path}: refusing a checkpoint that needs pickle code to load (torch.load(weights_only=True) "
                f"says: {reason}). Loading it would run code from the file. Where you trust it, re-save only its "
                "tensors: torch.save(torch.load(PATH, weights_only=False)['model'] or the model's state_dict(), "
                "'weights.pt')") from err
        except (RuntimeError, EOFError, OSError) as err:
            raise ReferenceCheckpointError(f"{path}: cannot be read as a torch checkpoint ({err})") from err
    state = _unwrap_state_dict(loaded, path)
    dropped = sorted(k for k in state if k.startswith(DROPPED_PREFIXES))
    return {k: v for k, v in state.items() if k not in dropped}, metadata, dropped


def _unwrap_state_dict(loaded: Any, path: Path) -> dict[str, Tensor]:
    if isinstance(loaded, Mapping) and not all(isinstance(v, Tensor) for v in loaded.values()):
        for key in ("model", "state_dict", "model_state_dict"):
            inner = loaded.get(key)
            if isinstance(inner, Mapping) and inner and all(isinstance(v, Tensor) for v in inner.values()):
                loaded = inner
                break
        else:
            others = sorted(str(k) for k, v in loaded.items() if not isinstance(v, Tensor))[:8]
            raise ReferenceCheckpointError(
                f"{path}: expected a state dict of tensors (or one under 'model'/'state_dict'); found non-tensor "
                f"entries {others}")
    if not isinstance(loaded, Mapping) or not loaded:
        raise ReferenceCheckpointError(f"{path}: expected a state dict of tensors, got {type(loaded).__name__}")
    state = {str(k): v for k, v in loaded.items()}
    if all(k.startswith("module.") for k in state):  # saved from a DataParallel/DDP wrapper
        state = {k[len("module."):]: v for k, v in state.items()}
    return state


def infer_model_config(
    state: Mapping[str, Tensor],
    *,
    behaviour: str = "reference",
    kind: str = "mfm",
    num_heads: int = DEFAULT_NUM_HEADS,
    activation: str = DEFAULT_ACTIVATION,
    source: str = "checkpoint",
) -> ModelConfig:
    """The :class:`ModelConfig` of a reference state dict, from its tensor shapes.

    behaviour: 'reference' (:data:`REFERENCE_BEHAVIOUR` of ``kind``) or 'ours' (:data:`OUR_BEHAVIOUR`).
    Refuses, naming the keys, a state dict with missing or unexpected keys (a truncated file, another
    architecture such as ``trans_dec``/``gru`` or ``rot_vel``, an unconditional model) or inconsistent shapes.
    """
    if kind not in REFERENCE_KINDS:
        raise ReferenceCheckpointError(f"unknown reference kind {kind!r}; known: {', '.join(REFERENCE_KINDS)}")
    if behaviour not in ("reference", "ours"):
        raise ReferenceCheckpointError(f"behaviour must be 'reference' or 'ours', got {behaviour!r}")
    pose = _required(state, "input_process.poseEmbedding.weight", source, ndim=2)
    latent_dim, feature_dim = pose.shape
    layers = sorted({int(m.group(1)) for k in state if (m := _LAYER_KEY.match(k))})
    if not layers:
        raise ReferenceCheckpointError(f"{source}: no seqTransEncoder.layers.* keys: not an MDM 'trans_enc' model "
                                       f"(keys start with {sorted({k.split('.')[0] for k in state})})")
    num_layers = layers[-1] + 1
    ff_dim = _required(state, "seqTransEncoder.layers.0.linear1.weight", source, ndim=2).shape[0]
    has_text, has_action = "embed_text.weight" in state, "embed_action.action_embedding" in state
    if has_text == has_action:
        what = "both embed_text and embed_action" if has_text else "neither embed_text nor embed_action"
        raise ReferenceCheckpointError(
            f"{source}: {what}: only text- or action-conditioned models map onto ours (unconditional MDM models "
            "are not supported)")
    cond_dim, num_actions = 512, 0
    if has_text:
        cond_dim = _required(state, "embed_text.weight", source, ndim=2).shape[1]
    else:
        num_actions = _required(state, "embed_action.action_embedding", source, ndim=2).shape[0]
    max_len = int(state["sequence_pos_encoder.pe"].shape[0]) if "sequence_pos_encoder.pe" in state else 5000
    try:
        config = ModelConfig(
            feature_dim=int(feature_dim), latent_dim=int(latent_dim), ff_dim=int(ff_dim), num_layers=num_layers,
            num_heads=num_heads, dropout=DEFAULT_DROPOUT, activation=activation, cond_dim=int(cond_dim),
            num_actions=int(num_actions), cond_drop_prob=DEFAULT_COND_DROP_PROB, max_len=max_len, norm_first=False,
            **(REFERENCE_BEHAVIOUR[kind] if behaviour == "reference" else OUR_BEHAVIOUR),
        )
    except ValueError as err:
        raise ReferenceCheckpointError(f"{source}: the inferred architecture is invalid ({err})") from err
    _check_keys_and_shapes(state, config, source)
    return config


def _required(state: Mapping[str, Tensor], key: str, source: str, *, ndim: int) -> Tensor:
    if key not in state:
        raise ReferenceCheckpointError(f"{source}: missing key {key!r}: not an MDM/MFM 'trans_enc' checkpoint")
    value = state[key]
    if value.dim() != ndim:
        raise ReferenceCheckpointError(f"{source}: {key} has shape {tuple(value.shape)}, expected {ndim} dims")
    return value


def key_map(config: ModelConfig) -> dict[str, str]:
    """Reference parameter name → ours, for a model of ``config``."""
    names = dict(_SHARED_PARAMS)
    names.update(_ACTION_PARAMS if config.is_action_model else _TEXT_PARAMS)
    for layer in range(config.num_layers):
        for theirs, ours in _LAYER_PARAMS.items():
            names[f"seqTransEncoder.layers.{layer}.{theirs}"] = f"layers.{layer}.{ours}"
    return names


def _check_keys_and_shapes(state: Mapping[str, Tensor], config: ModelConfig, source: str) -> None:
    from mfm.model import MotionFlowTransformer

    names = key_map(config)
    expected = set(names) | set(_POSITIONAL_TABLES)
    missing = sorted(set(names) - set(state))  # the tables are optional: ours are computed
    unexpected = sorted(set(state) - expected)
    if missing or unexpected:
        parts = []
        if missing:
            parts.append(f"missing {len(missing)} key(s): {', '.join(missing[:12])}{' …' if len(missing) > 12 else ''}")
        if unexpected:
            parts.append(f"unexpected {len(unexpected)} key(s): {', '.join(unexpected[:12])}"
                         f"{' …' if len(unexpected) > 12 else ''}")
        raise ReferenceCheckpointError(
            f"{source}: cannot map this state dict onto a {config.num_layers}-layer MDM 'trans_enc' model: "
            + "; ".join(parts))
    with torch.device("meta"):
        ours = MotionFlowTransformer(config).state_dict()
    wrong = [f"{theirs} {tuple(state[theirs].shape)} (expected {tuple(ours[mine].shape)})"
             for theirs, mine in names.items() if tuple(state[theirs].shape) != tuple(ours[mine].shape)]
    if wrong:
        raise ReferenceCheckpointError(f"{source}: inconsistent shapes: {'; '.join(wrong[:8])}")
    _check_finite(state, [*names, *(t for t in _POSITIONAL_TABLES if t in state)], source)
    for table in _POSITIONAL_TABLES:
        if table in state:
            _check_positional_table(state[table], config.latent_dim, f"{source}: {table}")


def _check_finite(state: Mapping[str, Tensor], keys: Sequence[str], source: str) -> None:
    """Every value of the tensors we take is finite: a NaN or inf weight would make every motion sampled from the
    converted model NaN (and a NaN positional table would pass the table check, whose comparisons are False)."""
    bad = []
    for key in keys:
        value = state[key]
        if value.is_floating_point() or value.is_complex():
            count = int((~torch.isfinite(value)).sum())
            if count:
                bad.append(f"{key} ({count} of {value.numel()} values)")
    if bad:
        raise ReferenceCheckpointError(f"{source}: non-finite (NaN or inf) weights in {len(bad)} tensor(s): "
                                       f"{', '.join(bad[:8])}{' …' if len(bad) > 8 else ''}; a model with them "
                                       "cannot be converted")


def _check_positional_table(table: Tensor, dim: int, what: str) -> None:
    """The reference's (rows, 1, d) sinusoid must be ours: we compute it instead of loading it."""
    if table.dim() != 3 or table.shape[1] != 1 or table.shape[2] != dim:
        raise ReferenceCheckpointError(f"{what} has shape {tuple(table.shape)}, expected (rows, 1, {dim})")
    ours = sinusoidal_embedding(torch.arange(table.shape[0]), dim)
    gap = float((table[:, 0, :].float() - ours).abs().max())
    if gap > POSITIONAL_TABLE_TOLERANCE:
        raise ReferenceCheckpointError(f"{what} differs from MDM's sinusoid table by up to {gap:.3g}: a model with "
                                       "another positional table cannot be converted")


def convert_state_dict(state: Mapping[str, Tensor], config: ModelConfig) -> dict[str, Tensor]:
    """Our state dict (fp32, contiguous) for the reference ``state`` of a model of ``config`` (checked first).

    With ``positional_table='stored'`` the reference's ``sequence_pos_encoder.pe`` becomes ``positional_table``
    (our computed table where the file has none)."""
    _check_keys_and_shapes(state, config, "checkpoint")
    converted = {ours: state[theirs].detach().float().contiguous().clone() for theirs, ours in key_map(config).items()}
    if config.positional_table == "stored":
        table = state.get("sequence_pos_encoder.pe")
        converted["positional_table"] = (
            table[:, 0, :].float().contiguous().clone() if table is not None
            else sinusoidal_embedding(torch.arange(config.max_len), config.latent_dim))
    return converted


def positional_table_gap(state: Mapping[str, Tensor], rows: int | None = None) -> float | None:
    """Largest |reference table − our computed table| over the first ``rows`` rows (all if None); None if the
    file holds no table."""
    table = state.get("sequence_pos_encoder.pe")
    if table is None:
        return None
    table = table[:rows, 0, :].float()
    return float((table - sinusoidal_embedding(torch.arange(table.shape[0]), table.shape[1])).abs().max())


def reference_layout(features: Tensor) -> Tensor:
    """Our (B, T, D) motion features in the reference's (B, D, 1, T) layout."""
    return features.permute(0, 2, 1).unsqueeze(2)


def from_reference_layout(features: Tensor) -> Tensor:
    """The reference's (B, D, 1, T) features (``njoints = D``, ``nfeats = 1``) as our (B, T, D)."""
    if features.dim() != 4 or features.shape[2] != 1:
        raise ValueError(f"expected reference features (B, D, 1, T), got {tuple(features.shape)}")
    return features.squeeze(2).permute(0, 2, 1)
