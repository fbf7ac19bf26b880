"""The results folder of a run: what each file is called, in one place (the runner writes them,
the services keep their state in them, exports and a later run's `--map DIR` read them).

A results folder is also a map: its place recognition's journal and keyframes and its
experience map's journal (with its checkpoint) are what `--map DIR` starts from. Frames of a
map that several sessions made are numbered across them: session k's frame f is
k·SESSION_FRAMES + f (session 0 is the first run, numbered as its source numbers its frames).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from services.common.settings import add_flag, setting

CONFIG = "config.json"
METRICS = "metrics.json"
MAP_LOG = "experience_map.log"           # expmap's journal (and MAP_LOG + ".checkpoint.npz")
TEMPLATE_LOG = "view_templates.log"      # loopclosure's journal (its keyframes: KEYFRAMES)
KEYFRAMES = "view_templates.keyframes"
GRID_CHECKPOINT = "gridcells.checkpoint.npz"
LOOP_CLOSURES = "loop_closures.csv"
LOGS = "logs"
# What a run leaves that the next run in the same folder would resume from (the services' state,
# with their side files such as the keyframes) or append to (the logs).
RUN_STATE_PATTERNS = ("experience_map.*", "view_templates.*", "gridcells.checkpoint*", "logs/*.log")

SESSION_FRAMES = 1_000_000_000   # frame numbers a session of a map may use


def session_base(session: int) -> int:
    """The first frame number of a map's session ``session``."""
    return session * SESSION_FRAMES


def session_of(frame: int) -> int:
    return frame // SESSION_FRAMES


def map_files(folder: Path) -> dict[str, Path]:
    """The files of the map a results folder holds, by role."""
    folder = Path(folder)
    return {"places": folder / TEMPLATE_LOG, "keyframes": folder / KEYFRAMES, "map": folder / MAP_LOG}


@dataclass(frozen=True)
class MapReuseParams:
    """A saved map used again, declared once: keys of `[run]`, `[loopclosure]` and `[expmap]`
    (GRIDSLAM_<SECTION>_MAP, _LOCALIZE) and the flags --map DIR and --localize."""

    map: Path | None = setting(None, help="start from the map of an earlier run's results folder (read only): this run "
                                          "is its next session, and its own results (the services' journals) the "
                                          "whole map")
    localize: bool = setting(False, help="with map: localise on the saved map only, storing nothing new")


def add_map_reuse_arguments(parser) -> None:
    """--map DIR and --localize, shared by run, demo and the loopclosure and expmap services."""
    add_flag(parser, MapReuseParams, "map", metavar="DIR")
    add_flag(parser, MapReuseParams, "localize")
