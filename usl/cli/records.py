"""``usl-records``: validate a dataset folder, summarise it (counts and a contact sheet), migrate a
folder of an older record schema (v1, v2) to the current one (v3) in place, export a split as COCO
instances JSON, or gather build folders made on separate machines into one.

    usl-records validate data/scene_shapes               # schema, checksums, masks, boxes, ids, cameras
    usl-records validate data/hypersim --split val --no-images
    usl-records info data/scene_shapes --sheet sheet.png # counts per split/category + a contact sheet
    usl-records migrate data/old_dataset                 # v1 or v2 -> v3 in place (atomic, resumable)
    usl-records export-coco data/scene_shapes --split val --out val_coco.json --images-dir val_images
    usl-records gather part0 part1 part2 --out data/hypersim  # --num-shards/--shard-index builds
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from usl.cli.common import common_options, make_parser

COMMAND = "usl-records"


def parser():
    p = make_parser(COMMAND, __doc__)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def command(name: str, help_text: str, **kwargs):
        return sub.add_parser(name, help=help_text, description=__doc__, formatter_class=p.formatter_class, **kwargs)

    check = command(
        "validate", "check a dataset folder against the record spec", parents=[common_options(quiet="no progress bar")]
    )
    check.add_argument("root", type=Path, help="dataset folder (with manifest.json)")
    check.add_argument("--split", action="append", help="only these splits (repeatable; default: all)")
    check.add_argument("--no-images", action="store_true", help="skip decoding every image (faster)")
    info = command("info", "counts per split and category, and a contact sheet PNG")
    info.add_argument("root", type=Path, help="dataset folder (with manifest.json)")
    info.add_argument("--sheet", type=Path, help="contact sheet path (default: ROOT/contact_sheet.png)")
    info.add_argument("--split", help="split for the contact sheet (default: the first)")
    info.add_argument("--scenes", type=int, default=4, help="scenes on the contact sheet")
    info.add_argument("--views", type=int, default=4, help="views per scene on the contact sheet")
    info.add_argument("--json", action="store_true", help="print counts as JSON")
    migrate = command(
        "migrate", "convert a schema v1 or v2 dataset folder to v3 in place (atomic, resumable; depth becomes an Image)"
    )
    migrate.add_argument("root", type=Path, help="dataset folder (with manifest.json)")
    coco = command("export-coco", "one split as COCO instances JSON (pycocotools, detectron2)")
    coco.add_argument("root", type=Path, help="dataset folder (with manifest.json)")
    coco.add_argument("--split", required=True, help="split to export, e.g. train")
    coco.add_argument("--out", type=Path, required=True, help="JSON file to write")
    coco.add_argument(
        "--images-dir",
        type=Path,
        help="also write the images here, as the JSON's file_name values name them (default: JSON only)",
    )
    merge = command("gather", "merge folders built apart (--num-shards/--shard-index) into one dataset")
    merge.add_argument("parts", nargs="+", type=Path, metavar="PART", help="build folders of one build")
    merge.add_argument("--out", type=Path, required=True, help="dataset folder to create (or complete)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    from usl.errors import UslError  # the tools below load pyarrow, OpenCV and (info) torch: after parsing

    try:
        if args.command == "gather":
            from usl.records.gather import gather

            summary = gather(args.parts, args.out, progress=True)
            print(f"{args.out}: copied {summary.copied} shard(s), kept {summary.kept}")
            if summary.missing:
                print(
                    f"usl-records: error: no part holds shard(s) {', '.join(summary.missing)}; build them "
                    "(same command, their --shard-index) and gather again",
                    file=sys.stderr,
                )
                return 1
            print(f"{args.out / 'manifest.json'} written")
            return 0
        if args.command == "validate":
            from usl.records.validate import validate_dataset

            problems = validate_dataset(
                args.root, args.split, decode_images=not args.no_images, progress=not args.quiet
            )
            for problem in problems:
                print(problem)
            print(f"{args.root}: {'valid' if not problems else f'{len(problems)} problem(s)'}")
            return 1 if problems else 0
        if args.command == "migrate":
            from usl.records.migrate import migrate_dataset

            print(migrate_dataset(args.root, progress=True).describe(args.root))
            return 0
        if args.command == "export-coco":
            from usl.records.coco import export_coco

            print(export_coco(args.root, args.split, args.out, args.images_dir, progress=True).describe())
            return 0
        from usl.records.info import contact_sheet, dataset_counts, format_counts

        counts = dataset_counts(args.root)
        print(json.dumps(counts, indent=1) if args.json else format_counts(counts))
        sheet = contact_sheet(
            args.root, args.sheet or args.root / "contact_sheet.png", args.split, args.scenes, args.views
        )
        print(f"contact sheet: {sheet}")
        return 0
    except UslError as exc:
        print(f"{COMMAND}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
