"""What rank 0 of a training run shows people: the tqdm postfix, ``metrics.jsonl``, W&B, TensorBoard, and
``loss.png`` when the run ends.

One record per logged step (:meth:`MetricsSink.log`) goes to every sink: a line of metrics.jsonl (the record as
it is, the source of truth: a resumed run drops the lines after its checkpoint, so the file holds every step
once), and its numeric entries as scalars to W&B (``train.wandb``) and TensorBoard (``train.tensorboard``, event
files under ``<out_dir>/tensorboard/``). Scalar names there: ``train/<key>`` (``train/loss``, ``train/lr``,
``train/grad_norm``, ``train/samples_per_s``, ...) and, for the validation keys ``val_<key>``, ``val/<key>``
(``val/loss``, ``val/samples``, ``val/time_s``). A resumed run's TensorBoard writer purges the events after the
step it resumed from (``purge_step``), as metrics.jsonl drops its lines.

When the run ends or stops (max_steps, a signal, an error after a logged step), :func:`write_loss_plot` draws
``<out_dir>/loss.png`` from metrics.jsonl (so a resumed run's curve is whole): the train loss, a smoothed line
through it, and the validation loss, against the step; a log-scale y axis when the losses span more than a
decade. Nothing here may stop a run: a W&B, TensorBoard or plotting failure is logged and training goes on.
"""

from __future__ import annotations

import importlib.util
import json
import logging
import math
import os
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from pipeline.config import ConfigError, TrainConfig, to_dict, wandb_mode

if TYPE_CHECKING:
    from tqdm import tqdm

    from mfm.model import ModelConfig
    from pipeline.distributed import Dist

logger = logging.getLogger(__name__)

METRICS_FILE = "metrics.jsonl"
TENSORBOARD_SUBDIR = "tensorboard"
LOSS_PLOT = "loss.png"
VAL_PREFIX = "val_"  # metrics.jsonl keys of the validation loss: val_loss, val_samples, val_weights, val_time_s
PREVIEW_PREFIX = "preview_"  # metrics.jsonl keys of the previews' plausibility medians (pipeline.training.previews)
PREVIEW_IMAGE_TAG = "preview/samples"  # the previews' contact sheets in TensorBoard and W&B


# ---------------------------------------------------------------------------------------------------------------
# Scalars and the TensorBoard writer
# ---------------------------------------------------------------------------------------------------------------


def tensorboard_available() -> bool:
    """Whether ``torch.utils.tensorboard`` can be imported (it needs the ``tensorboard`` package)."""
    return importlib.util.find_spec("tensorboard") is not None


def require_tensorboard(enabled: bool) -> None:
    """Refuse ``train.tensorboard=true`` without the tensorboard package (before training, on rank 0)."""
    if enabled and not tensorboard_available():
        raise ConfigError("train.tensorboard=true needs the tensorboard package, which is not installed: "
                          "pip install tensorboard (a dependency of this project), or set train.tensorboard=false")


def scalar_tags(record: Mapping[str, Any]) -> dict[str, float]:
    """The numeric, finite entries of a metrics record as W&B / TensorBoard scalars: ``train/<key>``, and
    ``val/<key>`` for ``val_<key>``, ``preview/<key>`` for ``preview_<key>``. ``step`` (the x axis), null values and
    strings are left out."""
    scalars = {}
    for key, value in record.items():
        if key == "step" or isinstance(value, bool) or not isinstance(value, (int, float)):
            continue
        if not math.isfinite(value):
            continue
        tag = f"train/{key}"
        for prefix in (VAL_PREFIX, PREVIEW_PREFIX):
            if key.startswith(prefix):
                tag = f"{prefix[:-1]}/{key[len(prefix):]}"
        scalars[tag] = float(value)
    return scalars


class TensorBoardWriter:
    """Scalars to TensorBoard event files in ``log_dir``, flushed at every write (people watch them live).

    ``start_step``: the step the run starts or resumes from; TensorBoard discards the events of later steps left
    by an earlier, killed process of this run (they are about to be trained again)."""

    def __init__(self, log_dir: Path, start_step: int = 0) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.log_dir = Path(log_dir)
        self._writer = SummaryWriter(log_dir=str(self.log_dir), purge_step=start_step + 1)

    def write(self, step: int, scalars: Mapping[str, float]) -> None:
        for tag, value in scalars.items():
            self._writer.add_scalar(tag, value, global_step=step)
        self._writer.flush()

    def write_image(self, step: int, tag: str, png: Path) -> None:
        from matplotlib.image import imread

        pixels = imread(str(png))[..., :3]  # (H, W, RGB[A]) floats in [0, 1]
        self._writer.add_image(tag, pixels, global_step=step, dataformats="HWC")
        self._writer.flush()

    def close(self) -> None:
        self._writer.close()


# ---------------------------------------------------------------------------------------------------------------
# The sinks
# ---------------------------------------------------------------------------------------------------------------


class MetricsSink:
    """Rank 0's outputs: the tqdm postfix, ``metrics.jsonl`` in the run folder, W&B (``train.wandb``: auto follows
    ``WANDB_MODE``, else offline; an explicit mode wins over ``WANDB_MODE``), TensorBoard (``train.tensorboard``),
    and ``loss.png`` on :meth:`close`. A W&B, TensorBoard or plotting failure is logged and never stops training.
    On other ranks every method is a no-op.
    """

    def __init__(self, out_dir: Path, cfg: TrainConfig, dist: Dist, model_config: ModelConfig, num_parameters: int,
                 start_step: int = 0):
        self.enabled = dist.is_main
        self.out_dir = Path(out_dir)
        self.jsonl = None
        self.wandb_run = None
        self.tensorboard: TensorBoardWriter | None = None
        if not self.enabled:
            return
        metrics_path = self.out_dir / METRICS_FILE
        drop_records_after(metrics_path, start_step)
        self.jsonl = open(metrics_path, "a", encoding="utf-8")
        dist.log0("model: %.2f M parameters; world size %d; device %s; precision %s",
                  num_parameters / 1e6, dist.world_size, dist.device, dist.mixed_precision, log=logger)
        mode = wandb_mode(cfg.train.wandb)
        if mode != "disabled":
            try:
                import wandb

                os.environ.setdefault("WANDB_DIR", str(out_dir))
                self.wandb_run = wandb.init(
                    project=cfg.train.wandb_project, mode=mode, dir=str(out_dir), config=to_dict(cfg),
                    name=self.out_dir.name, resume="allow", id=_wandb_run_id(self.out_dir),
                )
            except Exception as err:  # logging must never take the run down
                logger.warning("W&B disabled for this run: %s", err)
                self.wandb_run = None
        if cfg.train.tensorboard:
            try:
                self.tensorboard = TensorBoardWriter(self.out_dir / TENSORBOARD_SUBDIR, start_step)
                dist.log0("TensorBoard: tensorboard --logdir %s", self.tensorboard.log_dir, log=logger)
            except Exception as err:  # noqa: BLE001 - the package was checked at start; a full disk is not fatal
                logger.warning("TensorBoard disabled for this run: %s", err)
                self.tensorboard = None

    def log(self, record: dict[str, Any], progress: tqdm) -> None:
        """Write one record (a train log step, a validation, or both at one step) to every sink."""
        if not self.enabled:
            return
        postfix = {}
        if "loss" in record:
            postfix["loss"] = "skipped" if record["loss"] is None else f"{record['loss']:.4f}"
            postfix["sps"] = f"{record['samples_per_s']:.0f}"
            postfix["wait"] = f"{record['data_wait_frac']:.0%}"
            if record.get("mfu") is not None:
                postfix["mfu"] = f"{record['mfu']:.1%}"
        if record.get("val_loss") is not None:
            postfix["val"] = f"{record['val_loss']:.4f}"
        if postfix:
            progress.set_postfix(postfix)
        self.jsonl.write(json.dumps(record) + "\n")
        self.jsonl.flush()
        scalars = scalar_tags(record)
        if self.wandb_run is not None:
            self.wandb_run.log(scalars, step=record["step"])
        if self.tensorboard is not None:
            try:
                self.tensorboard.write(record["step"], scalars)
            except Exception as err:  # noqa: BLE001 - logging must never take the run down
                logger.warning("TensorBoard disabled for the rest of this run: %s", err)
                self._close_tensorboard()

    def log_image(self, step: int, tag: str, png: Path) -> None:
        """An image file (a preview's contact sheet) to W&B and TensorBoard under ``tag``."""
        if not self.enabled:
            return
        if self.wandb_run is not None:
            try:
                import wandb

                self.wandb_run.log({tag: wandb.Image(str(png))}, step=step)
            except Exception as err:  # noqa: BLE001 - logging must never take the run down
                logger.warning("W&B: could not log %s: %s", png, err)
        if self.tensorboard is not None:
            try:
                self.tensorboard.write_image(step, tag, png)
            except Exception as err:  # noqa: BLE001 - logging must never take the run down
                logger.warning("TensorBoard disabled for the rest of this run: %s", err)
                self._close_tensorboard()

    def close(self) -> None:
        """Close the sinks, then draw loss.png from metrics.jsonl (when it holds a loss)."""
        if not self.enabled:
            return
        if self.jsonl is not None:
            self.jsonl.close()
            self.jsonl = None
        if self.wandb_run is not None:
            self.wandb_run.finish()
            self.wandb_run = None
        self._close_tensorboard()
        try:
            write_loss_plot(self.out_dir / METRICS_FILE, self.out_dir / LOSS_PLOT)
        except Exception as err:  # noqa: BLE001 - a plot is never worth a failed run
            logger.warning("could not draw %s: %s: %s", self.out_dir / LOSS_PLOT, type(err).__name__, err)

    def _close_tensorboard(self) -> None:
        writer, self.tensorboard = self.tensorboard, None
        if writer is not None:
            try:
                writer.close()
            except Exception as err:  # noqa: BLE001
                logger.warning("closing the TensorBoard writer failed: %s", err)


def drop_records_after(metrics_path: Path, step: int) -> None:
    """Keep only the records of steps <= ``step`` (the step a run starts or resumes from): the steps after it are
    about to be trained (again), and a killed run may have logged some of them, or left a torn last line."""
    if not metrics_path.exists():
        return
    text = metrics_path.read_text(encoding="utf-8")
    kept = []
    for line in text.splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(record, dict) and isinstance(record.get("step"), int) and record["step"] <= step:
            kept.append(line + "\n")
    if "".join(kept) == text:
        return  # nothing to drop: no rewrite (on a nearly full disk, no temporary copy either)
    tmp = metrics_path.with_name(metrics_path.name + ".tmp")
    tmp.write_text("".join(kept), encoding="utf-8")
    os.replace(tmp, metrics_path)


def _wandb_run_id(out_dir: Path) -> str:
    """A stable W&B id per run folder so a resumed run continues the same W&B run."""
    id_file = out_dir / "wandb_id.txt"
    if id_file.exists():
        return id_file.read_text().strip()
    import uuid

    run_id = uuid.uuid4().hex[:12]
    id_file.write_text(run_id)
    return run_id


# ---------------------------------------------------------------------------------------------------------------
# loss.png
# ---------------------------------------------------------------------------------------------------------------


def read_metrics(metrics_path: Path) -> list[dict[str, Any]]:
    """The records of a metrics.jsonl (a torn or foreign line is passed over), in file order."""
    records = []
    for line in Path(metrics_path).read_text(encoding="utf-8").splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(record, dict) and isinstance(record.get("step"), int):
            records.append(record)
    return records


def _points(records: list[dict[str, Any]], key: str) -> tuple[list[int], list[float]]:
    pairs = sorted((r["step"], float(r[key])) for r in records
                   if isinstance(r.get(key), (int, float)) and not isinstance(r.get(key), bool)
                   and math.isfinite(r[key]))
    return [s for s, _ in pairs], [v for _, v in pairs]


def smooth(values: list[float], window: int, log: bool = False) -> list[float]:
    """Centred moving average over ``window`` points (shorter at the ends), geometric with ``log`` (for a
    log-scale axis): no lag behind a falling curve, unlike a trailing average."""
    import numpy as np

    x = np.asarray(values, dtype=np.float64)
    if log:
        x = np.log(x)
    half = max(window, 1) // 2
    sums = np.concatenate([[0.0], np.cumsum(x)])
    index = np.arange(len(x))
    lo, hi = np.maximum(index - half, 0), np.minimum(index + half + 1, len(x))
    out = (sums[hi] - sums[lo]) / (hi - lo)
    return (np.exp(out) if log else out).tolist()


def write_loss_plot(metrics_path: Path, png_path: Path) -> Path | None:
    """Draw the train loss (points, and a centred moving average through them when there are 10 or more), and the
    validation loss against the step from ``metrics_path`` into ``png_path`` (written atomically); the y axis is
    logarithmic when the losses span more than a decade. Returns None (and writes nothing) when the file holds
    no loss yet. Uses matplotlib's Agg canvas directly: no pyplot, the process's backend is left alone."""
    metrics_path, png_path = Path(metrics_path), Path(png_path)
    if not metrics_path.exists():
        return None
    records = read_metrics(metrics_path)
    train_steps, train_loss = _points(records, "loss")
    val_steps, val_loss = _points(records, "val_loss")
    if not train_loss and not val_loss:
        return None
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7.5, 4.5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    values = train_loss + val_loss
    log_scale = min(values) > 0 and max(values) > 10 * min(values)
    if train_loss:
        dense = len(train_loss) >= 10
        ax.plot(train_steps, train_loss, color="C0", alpha=0.35 if dense else 1.0, linewidth=0.8,
                marker=None if dense else "o", markersize=3, label="train loss")
        if dense:
            window = max(3, len(train_loss) // 25)
            ax.plot(train_steps, smooth(train_loss, window, log=log_scale), color="C0", linewidth=1.8,
                    label=f"train loss (mean of {window} points)")
    if val_loss:
        weights = next((r.get("val_weights") for r in reversed(records) if "val_loss" in r), None)
        ax.plot(val_steps, val_loss, color="C1", marker="o", markersize=3.5, linewidth=1.4,
                label="val loss" + (f" ({weights} weights)" if weights else ""))
    if log_scale:
        ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    last = max(train_steps[-1:] + val_steps[-1:])
    ax.set_title(f"{metrics_path.parent.name}: step {last}", fontsize=10)
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    tmp = png_path.with_name(f".{png_path.stem}.{os.getpid()}.tmp.png")
    fig.savefig(tmp, dpi=110)
    os.replace(tmp, png_path)
    return png_path
