"""Where benchmarks write their figures: bench/results/NAME.json (gitignored)."""

from __future__ import annotations

import json
from pathlib import Path

RESULTS = Path(__file__).resolve().parents[1] / "results"


def write_results(name: str, figures: dict) -> Path:
    """Write figures as bench/results/NAME.json and return the path."""
    RESULTS.mkdir(parents=True, exist_ok=True)
    out = RESULTS / f"{name}.json"
    out.write_text(json.dumps(figures, indent=2) + "\n")
    return out
