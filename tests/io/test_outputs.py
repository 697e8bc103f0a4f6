"""metrics.json is strict JSON: what could not be computed is null, never NaN or Infinity."""
import json

import numpy as np
import pytest

from surfelwarp.io.outputs import FrameRecord, RunOutputs, finite_or_null
from surfelwarp.tracking.tracker import TrackingCounts


def strict(text: str):
    def refuse(name):
        raise ValueError(f"not JSON: {name}")
    return json.loads(text, parse_constant=refuse)


def test_non_finite_values_are_null(tmp_path):
    counts = TrackingCounts(correspondences=0, data_rmse_m=float("inf"), rigid_rmse_m=float("nan"), rigid_iterations=0,
                            rigid_degenerate_directions=0, silhouette_points=0)
    record = FrameRecord(3, 0, np.eye(4), {"read": 0.01, "total": 0.02}, energy=float("nan"), details=(counts,))
    outputs = RunOutputs(tmp_path, "surfelwarp", tmp_path / "seq", {"k": [1.0, float("-inf")]})
    outputs.add_frame(record)
    frame = strict(outputs.write_metrics().read_text())["frames"][0]
    assert frame["rigid_rmse_m"] is None and frame["data_rmse_m"] is None and frame["energy"] is None
    assert frame["seconds"] == {"read": 0.01, "total": 0.02} and frame["correspondences"] == 0
    assert strict((tmp_path / "metrics.json").read_text())["config"] == {"k": [1.0, None]}
    with pytest.raises(ValueError):
        strict('{"a": NaN}')        # the check above can fail


def test_finite_values_pass_unchanged():
    doc = {"a": 1.5, "b": [0, 2.5e-300, True, "x", None], "c": {"d": -0.0}}
    assert json.dumps(finite_or_null(doc)) == json.dumps(doc)      # the sign of -0.0 too
