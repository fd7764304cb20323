"""Convert a published MFM or MDM checkpoint into a checkpoint folder of ours (sampling, editing, evaluation).

    python launch/convert_checkpoint.py --from mfm save/humanml_trans_enc_512/model000500000.pt \
        --dataset humanml3d --reference-root path/to/motionfm --out runs/mfm-humanml3d
    python launch/convert_checkpoint.py --from mdm model000475000.pt --dataset humanml3d \
        --mean HumanML3D/Mean.npy --std HumanML3D/Std.npy --out runs/mdm-humanml3d
    python launch/sample.py --checkpoint runs/mfm-humanml3d --text "a person walks forward." --seconds 4 \
        --text-weights ~/.cache/clip/ViT-B-32.pt --out samples

The file is read with torch.load(weights_only=True) (one that needs pickle code is refused) or as .safetensors.
The architecture comes from the tensor shapes (width, layers, FF size, feature size, text or action conditioning);
the heads from the file's metadata or MDM/MFM's fixed 4 (--num-heads). --behaviour reference (default) reproduces the
reference forward pass (time on its 1/1000 grid, attention over padded frames, its stored positional table);
--behaviour ours uses our model's defaults. See pipeline/training/convert.py for what the folder records.
Exit code: 0 done, 2 refused (one line on stderr: unreadable file, keys that do not map, NaN or inf weights (the
tensors named), missing Mean/Std, an output folder that is not new), 1 other errors.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from mfm.reference_weights import REFERENCE_KINDS, ReferenceCheckpointError
from pipeline.config import ConfigError
from pipeline.training.convert import (
    REFERENCE_DATASETS,
    ConversionError,
    ConversionRequest,
    convert_checkpoint,
    describe,
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--from", dest="kind", required=True, choices=REFERENCE_KINDS, help="which reference code")
    parser.add_argument("source", type=Path, help="the reference checkpoint (.pt or .safetensors)")
    parser.add_argument("--dataset", required=True, choices=sorted(REFERENCE_DATASETS))
    parser.add_argument("--out", required=True, type=Path, help="a new run folder for the converted checkpoint")
    parser.add_argument("--mean", type=Path, help="the dataset's Mean.npy (default: under --reference-root)")
    parser.add_argument("--std", type=Path, help="the dataset's Std.npy (default: under --reference-root)")
    parser.add_argument("--reference-root", type=Path, default=Path("."),
                        help="a reference repository checkout holding dataset/HumanML3D/ or dataset/KIT-ML/")
    parser.add_argument("--clip-weights", help="the CLIP ViT-B/32 file prompts will be encoded with (default: "
                        "OpenAI's ViT-B-32.pt, recorded by its sha256)")
    parser.add_argument("--behaviour", choices=("reference", "ours"), default="reference")
    parser.add_argument("--num-heads", type=int, help="attention heads (default: file metadata, else 4)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    request = ConversionRequest(kind=args.kind, source=args.source, dataset=args.dataset, out=args.out,
                                mean=args.mean, std=args.std, reference_root=args.reference_root,
                                clip_weights=args.clip_weights, behaviour=args.behaviour, num_heads=args.num_heads)
    try:
        folder = convert_checkpoint(request)
    except (ConversionError, ReferenceCheckpointError, ConfigError) as err:
        print(f"convert_checkpoint: {err}", file=sys.stderr)
        return 2
    from pipeline.generation.inference import load_trained_model

    trained = load_trained_model(folder)  # what every downstream job does: proves the folder loads
    print(f"{folder}: {describe(trained.model_config)}; objective {trained.objective}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
