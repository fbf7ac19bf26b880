"""The exported JSON Schemas in schemas/json/ must match the models (regenerate with
`gridslam schemas export`)."""

from schemas import MESSAGES
from services.cli.schemas import SCHEMA_DIR, render


def test_exported_schemas_are_current():
    expected = render()
    assert len(expected) == len(MESSAGES)
    on_disk = {path.name: path.read_text() for path in SCHEMA_DIR.glob("*.schema.json")}
    stale = sorted(name for name in expected if on_disk.get(name) != expected[name])
    extra = sorted(set(on_disk) - set(expected))
    assert not stale and not extra, (
        f"schemas/json is stale (changed: {stale}, unknown: {extra}); run `gridslam schemas export`")
