"""The runner's Supervisor quotes why a run stalls: the newest warning among its children's last
lines (a stereo estimator fed a monocular source rejects every frame, and says so only in its log)."""

from pathlib import Path

from services.pipeline.runner import Child, Supervisor


def supervisor_with(tails: dict[str, list[str]]) -> Supervisor:
    supervisor = Supervisor(Path("logs"))
    for name, lines in tails.items():
        child = Child(name, [], Path(f"logs/{name}.log"))
        child.tail.extend(lines)
        supervisor.children[name] = child
    return supervisor


def test_the_newest_warning_of_the_named_children_is_quoted_with_its_name():
    supervisor = supervisor_with({
        "source": ["2026-12-01 02:46:58,100 WARNING services.source.service: source: sending frames 0-7 again",
                   "2026-12-01 02:47:09,000 INFO services.source.service: source: waiting"],
        "egomotion": ["2026-12-01 02:46:59,578 WARNING services.common.service: egomotion: rejected seq 0 (6 so far): "
                      "stereo estimator: frame 0 has no right image (the source is monocular)",
                      "2026-12-01 02:47:08,000 INFO services.common.service: still here"],
        "gridcells": ["2026-12-01 02:46:50,000 ERROR services.gridcells.service: cannot write the checkpoint"],
        "router": ["2026-12-01 02:47:10,000 WARNING zenoh: a later warning of a child not asked about"],
    })
    assert supervisor.newest_warning(["source", "egomotion", "gridcells"]) == (
        "egomotion: rejected seq 0 (6 so far): stereo estimator: frame 0 has no right image (the source is monocular)")
    assert supervisor.newest_warning(["gridcells"]) == "gridcells: cannot write the checkpoint"
    assert supervisor.newest_warning(["viewer"]) is None
    assert supervisor_with({"source": ["2026-12-01 02:47:09,000 INFO x: fine"]}).newest_warning(["source"]) is None
