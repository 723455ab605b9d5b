"""The pipeline's numbers are unchanged, bit for bit, against the golden record.

`tests/golden/record.py` wrote `tests/golden/pipeline.json` from a quick staged
collection and a short lemniscate with all six conditions (see its docstring for
when to re-record). This test runs the same command lines and compares every log
digest, checkpoint digest and metric exactly: a refactor that moves any number,
however little, fails here.
"""

import importlib.util
import json
from pathlib import Path

_spec = importlib.util.spec_from_file_location("golden_record", Path(__file__).parent / "golden" / "record.py")
record = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(record)


def test_pipeline_matches_golden_record(tmp_path):
    record.run_pipeline(tmp_path)
    got = record.summarize(tmp_path)
    want = json.loads(record.GOLDEN.read_text())
    assert got["staged"]["logs"].keys() == want["staged"]["logs"].keys()
    changed = [k for k, v in want["staged"]["logs"].items() if got["staged"]["logs"][k] != v]
    assert not changed, f"flight logs differ from the golden record: {changed}"
    assert got["staged"]["checkpoints"] == want["staged"]["checkpoints"]
    for key in ("stages", "val_rmse", "noise_floor"):
        assert got["staged"][key] == want["staged"][key], key
    assert got["lemniscate"] == want["lemniscate"]
