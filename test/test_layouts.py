"""The Foxglove and PlotJuggler layouts in config/ name the node's real topics and fields."""

import json
import xml.etree.ElementTree as ET

import pytest

from .conftest import ROOT

msgs = pytest.importorskip("spm_sysid_interfaces.msg",
                           reason="the interfaces are not built here (make test builds them)")

TOPICS = {"/spm_sysid/prediction": msgs.Prediction, "/spm_sysid/validity": msgs.Validity}


def _field(path: str, sep: str):
    """(message class, field) of a path such as /spm_sysid/prediction.measured."""
    topic = next(t for t in TOPICS if path.startswith(t + sep))
    return TOPICS[topic], path[len(topic) + 1:]


def test_the_foxglove_layout_plots_prediction_and_shows_validity():
    doc = json.loads((ROOT / "config" / "foxglove_layout.json").read_text())
    paths = [p["value"] for panel in doc["configById"].values() for p in panel.get("paths", [])]
    assert "/spm_sysid/prediction.measured" in paths
    assert "/spm_sysid/prediction.predicted" in paths
    assert "/spm_sysid/validity.state_name" in paths
    for path in paths:
        cls, name = _field(path, ".")
        assert name in cls.get_fields_and_field_types(), path

    def panels(node):  # every panel the layout tree places
        return [node] if isinstance(node, str) else panels(node["first"]) + panels(
            node["second"])

    assert sorted(panels(doc["layout"])) == sorted(doc["configById"])


def test_the_plotjuggler_layout_subscribes_and_plots_the_same():
    root = ET.parse(ROOT / "config" / "plotjuggler_layout.xml").getroot()
    topics = [t.get("name") for t in root.iter("topic")]
    assert sorted(topics) == sorted(TOPICS)
    curves = [c.get("name") for c in root.iter("curve")]
    assert {"/spm_sysid/prediction/measured", "/spm_sysid/prediction/predicted",
            "/spm_sysid/validity/state"} <= set(curves)
    for curve in curves:
        cls, name = _field(curve, "/")
        assert name in cls.get_fields_and_field_types(), curve
