"""`gridslam vocabulary`: train the visual vocabulary of the `bow` place recognition
(services/loopclosure/vocabulary.py) on the ORB features of a set of frames.

With no --source it trains the vocabulary gridslam ships, from frames it renders itself (so that
nothing in the package comes from a dataset), and writes it where the package keeps it: the
same command on the same tree gives the same file."""

from __future__ import annotations

import logging
from pathlib import Path

from services.common.errors import ConfigError

log = logging.getLogger(__name__)

# The frames the shipped vocabulary is trained on: SPEC@PRESET/EVERY (every EVERY-th frame).
SHIPPED_TRAINING = ("synthetic:0@synthetic/5", "synthetic:1@synthetic/5", "synthetic:2@synthetic/5", "synthetic:0@campus/15")


def register(subparsers) -> None:
    parser = subparsers.add_parser("vocabulary", help="train the visual vocabulary of the bow place recognition")
    parser.add_argument("--source", action="append", metavar="SPEC[@PRESET][/EVERY]",
                        help="frames to train on, repeatable: a source spec, its preset and every how many frames "
                             f"(default: the shipped vocabulary's, {' '.join(SHIPPED_TRAINING)})")
    parser.add_argument("--branching", type=int, default=16, help="children per node of the tree (default 16)")
    parser.add_argument("--depth", type=int, default=4, help="levels of the tree: branching^depth words (default 4)")
    parser.add_argument("--out", type=Path, help="vocabulary file to write (default: the one the package ships)")
    parser.set_defaults(func=run)


def parse_training(text: str) -> tuple[str, str | None, int]:
    """SPEC[@PRESET][/EVERY] → (spec, preset, every)."""
    rest, slash, every = text.rpartition("/")
    if not slash or not every.isdigit():
        rest, every = text, "1"
    if int(every) < 1:
        raise ConfigError(f"--source {text}: EVERY must be a positive integer")
    spec, _, preset = rest.partition("@")
    return spec, preset or None, int(every)


def run(args) -> int:
    from services.loopclosure.geometry import ClosureGeometry
    from services.loopclosure.vocabulary import DEFAULT_FILE, train
    from services.source.spec import open_source

    sources = args.source or list(SHIPPED_TRAINING)
    geometry = ClosureGeometry()
    descriptors = []
    for text in sources:
        spec, preset, every = parse_training(text)
        frames = open_source(spec, preset=preset)
        for index in range(0, len(frames), every):
            descriptors.append(geometry.features(frames[index].left).descriptors)
        log.info("%s: %d frames", text, len(range(0, len(frames), every)))
    vocabulary = train(descriptors, args.branching, args.depth, trained_on=" ".join(sources))
    out = args.out or DEFAULT_FILE
    out.parent.mkdir(parents=True, exist_ok=True)
    vocabulary.save(out)
    print(f"{out}: {vocabulary.words} words from {sum(len(d) for d in descriptors)} features of {len(descriptors)} "
          f"frames ({out.stat().st_size / 1024:.0f} KiB)")
    return 0
