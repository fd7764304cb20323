"""Data sources: where clips come from before feature extraction (``--source NAME``).

A source is a picklable class built from keyword options (``build_source(name, root, **options)``):

* ``name`` and ``skeleton`` (a name in ``mfm.skeleton.SKELETONS``);
* ``list_items() -> list[str]``: cheap, deterministic, sorted item references (ids or relative paths),
  including every item the dataset lists (a split file, an index) whose data is absent;
* ``load(item) -> Clip | SkippedInput``: runs in a worker process and never raises for bad input; it
  returns ``SkippedInput`` with reason ``unreadable``, ``missing_file``, ``bad_shape`` (complex-valued
  arrays too), ``nan_frames`` or ``no_captions``. Caption lines it cannot read are counted by reason in
  ``Clip.dropped_captions``. Length filtering, resampling to the skeleton's fps and feature errors belong
  to the processing stage;
* optionally ``ignored_files() -> list[str]``: what the source's folder holds but never reads (names that
  are not of the layout's pattern), listed in the skip report.
* optionally ``caption_problems() -> list[SkippedInput]``: caption entries of a file the source reads up front
  (AMASS's JSON/CSV caption map) that it dropped, each naming the file, the entry and the reason; they are
  counted in their clips' ``dropped_captions``, and ``--strict`` stops at the first.

``Clip.joints`` are (T, J, 3) float32 in the skeleton's units at the source's own fps; caption spans are
in seconds. Sources whose skeleton has no built-in bone lengths (KIT) also offer ``target_skeleton()``.
"""

from __future__ import annotations

import inspect
from pathlib import Path
from typing import Protocol, runtime_checkable

from preprocess.clip import Clip, SkippedInput
from preprocess.sources.amass import AMASSSource
from preprocess.sources.deepmimic import DeepMimicSource
from preprocess.sources.humanml3d import HumanML3DSource
from preprocess.sources.kit import KITSource
from preprocess.sources.synthetic import SyntheticSource


@runtime_checkable
class Source(Protocol):
    name: str
    skeleton: str

    def list_items(self) -> list[str]: ...

    def load(self, item: str) -> Clip | SkippedInput: ...


SOURCES: dict[str, type] = {
    cls.name: cls for cls in (HumanML3DSource, KITSource, AMASSSource, DeepMimicSource, SyntheticSource)
}


def build_source(name: str, root: str | Path | None = None, **options: object) -> Source:
    """The source called ``name``, built on ``root`` with its keyword ``options``. Unknown names and
    options are errors that list what is accepted."""
    try:
        cls = SOURCES[name]
    except KeyError:
        raise ValueError(f"unknown source {name!r}; known: {sorted(SOURCES)}") from None
    accepted = [
        p.name for p in inspect.signature(cls.__init__).parameters.values() if p.kind is inspect.Parameter.KEYWORD_ONLY
    ]
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise ValueError(f"source {name!r} has no option(s) {unknown}; it accepts {accepted}")
    return cls(root=root, **options)


__all__ = ["SOURCES", "Source", "build_source"]
