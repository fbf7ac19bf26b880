"""`gridslam schemas export`: write the JSON Schema of every wire message into schemas/json/."""

from __future__ import annotations

import json
from pathlib import Path

from schemas import MESSAGES

SCHEMA_DIR = Path(__file__).resolve().parents[2] / "schemas" / "json"


def render() -> dict[str, str]:
    """File name → JSON Schema text, for every message."""
    return {
        f"{model.KIND}.schema.json": json.dumps(model.model_json_schema(), indent=2, sort_keys=True) + "\n"
        for model in MESSAGES
    }


def export(directory: Path = SCHEMA_DIR) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in render().items():
        path = directory / name
        path.write_text(text)
        written.append(path)
    return written


def register(subparsers) -> None:
    parser = subparsers.add_parser("schemas", help="export the JSON Schema of every message")
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    export_parser = actions.add_parser("export", help="write schemas/json/<Message>.schema.json")
    export_parser.add_argument("--out", type=Path, default=SCHEMA_DIR, help=f"folder (default {SCHEMA_DIR})")
    parser.set_defaults(func=run)


def run(args) -> int:
    for path in export(args.out):
        print(path)
    return 0
