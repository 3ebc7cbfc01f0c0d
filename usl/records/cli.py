"""``usl-records``: validate a dataset folder, summarise it (counts and a contact sheet), migrate a
schema v1 folder to v2 in place, export a split as COCO instances JSON, or gather build folders
made on separate machines into one."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .errors import UslError
from .coco import export_coco
from .gather import gather
from .info import contact_sheet, dataset_counts, format_counts
from .migrate import migrate_dataset
from .validate import validate_dataset


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="usl-records", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    check = sub.add_parser("validate", help="check a dataset folder against the record spec")
    check.add_argument("root", type=Path)
    check.add_argument("--split", action="append", help="only these splits (repeatable)")
    check.add_argument("--no-images", action="store_true", help="skip decoding every image (faster)")
    info = sub.add_parser("info", help="counts per split and category, and a contact sheet PNG")
    info.add_argument("root", type=Path)
    info.add_argument("--sheet", type=Path, help="contact sheet path (default: ROOT/contact_sheet.png)")
    info.add_argument("--split", help="split for the contact sheet (default: the first)")
    info.add_argument("--scenes", type=int, default=4)
    info.add_argument("--views", type=int, default=4)
    info.add_argument("--json", action="store_true", help="print counts as JSON")
    migrate = sub.add_parser("migrate", help="convert a schema v1 dataset folder to v2 in place (atomic, resumable)")
    migrate.add_argument("root", type=Path)
    coco = sub.add_parser("export-coco", help="one split as COCO instances JSON (pycocotools, detectron2)")
    coco.add_argument("root", type=Path)
    coco.add_argument("--split", required=True, help="split to export, e.g. train")
    coco.add_argument("--out", type=Path, required=True, help="JSON file to write")
    coco.add_argument("--images-dir", type=Path,
                      help="also write the images here, as the JSON's file_name values name them (default: JSON only)")
    merge = sub.add_parser("gather", help="merge folders built apart (--num-shards/--shard-index) into one dataset")
    merge.add_argument("parts", nargs="+", type=Path, metavar="PART", help="build folders of one build")
    merge.add_argument("--out", type=Path, required=True, help="dataset folder to create (or complete)")
    args = parser.parse_args(argv)
    try:
        if args.command == "gather":
            summary = gather(args.parts, args.out, progress=True)
            print(f"{args.out}: copied {summary.copied} shard(s), kept {summary.kept}")
            if summary.missing:
                print(f"usl-records: error: no part holds shard(s) {', '.join(summary.missing)}; build them "
                      "(same command, their --shard-index) and gather again", file=sys.stderr)
                return 1
            print(f"{args.out / 'manifest.json'} written")
            return 0
        if args.command == "validate":
            problems = validate_dataset(args.root, args.split, decode_images=not args.no_images, progress=True)
            for problem in problems:
                print(problem)
            print(f"{args.root}: {'valid' if not problems else f'{len(problems)} problem(s)'}")
            return 1 if problems else 0
        if args.command == "migrate":
            print(migrate_dataset(args.root, progress=True).describe(args.root))
            return 0
        if args.command == "export-coco":
            print(export_coco(args.root, args.split, args.out, args.images_dir, progress=True).describe())
            return 0
        counts = dataset_counts(args.root)
        print(json.dumps(counts, indent=1) if args.json else format_counts(counts))
        sheet = contact_sheet(args.root, args.sheet or args.root / "contact_sheet.png", args.split, args.scenes, args.views)
        print(f"contact sheet: {sheet}")
        return 0
    except UslError as exc:
        print(f"usl-records: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
