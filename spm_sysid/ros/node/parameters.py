"""The node's parameters: declared from the settings schema, checked when set, held.

The ROS 2 demos' pattern (``demo_nodes_py``'s ``set_parameters_callback``): a
change is checked in one callback and the accepted values -- with the job
settings and channels built from them while checking -- are held in another,
so the node always holds validated settings and never re-reads or re-checks
them.
"""

from __future__ import annotations

from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.node import Node

from ...core.files import check_writable_file
from ...core.io.channels import check_roles, parse_channels
from ...core.jobs import JobSettings
from ...core.settings import SETTINGS, Setting, check, node_settings, parse_text

__all__ = ["NodeParameters", "parameter_descriptor", "unknown_overrides", "unknown_text"]


def unknown_overrides(node: Node) -> list[str]:
    """Parameters given to ``node`` (``-p``, ``--params-file``) that it does not declare.

    ROS keeps such values unused and says nothing: a misspelled ``input_topc``
    would leave the default topic in place. QoS overrides (``qos_overrides.*``)
    are ROS's own and left out.
    """
    given = getattr(node, "_parameter_overrides", {})  # rclpy's values for this node
    return sorted(n for n in given
                  if not node.has_parameter(n) and not n.startswith("qos_overrides."))


def unknown_text(name: str, known: list[str], where: str) -> str:
    """A warning for one unknown parameter, with the nearest of ``known`` (``where``: a list)."""
    from difflib import get_close_matches

    near = get_close_matches(name, known, n=1)
    return (f"parameter {name!r} is not one of this node's" + (
        f" (did you mean {near[0]!r}?)" if near else "") + f": ignored (the parameters: "
        f"{where})")


def parameter_descriptor(s: Setting) -> ParameterDescriptor:
    """A node parameter's descriptor from its setting (range, read-only, description)."""
    d = ParameterDescriptor(description=s.help, read_only=s.read_only)
    if s.kind is int and s.low is not None:
        d.integer_range = [IntegerRange(from_value=int(s.low), to_value=int(s.high), step=1)]
    elif s.kind is float and s.low is not None:
        d.floating_point_range = [FloatingPointRange(from_value=float(s.low),
                                                     to_value=float(s.high), step=0.0)]
    if s.choices:
        d.additional_constraints = "one of " + ", ".join(s.choices)
    return d


class NodeParameters:
    """The schema's node settings as parameters of ``node``; ``values`` and ``job`` are valid.

    Raises
    ------
    ValueError
        At start, a parameter value that would make an identification impossible.
    """

    def __init__(self, node: Node) -> None:
        self.node = node
        for s in node_settings():
            node.declare_parameter(s.name, s.default, parameter_descriptor(s))
        self.unknown = unknown_overrides(node)  # counted in /diagnostics too
        for name in self.unknown:
            node.get_logger().warning(unknown_text(
                name, [s.name for s in node_settings()],
                "spm-sysid settings, config/sysid_node.yaml"))
        node.add_on_set_parameters_callback(self._check_change)
        node.add_post_set_parameters_callback(self._hold_change)
        values = {s.name: node.get_parameter(s.name).value for s in node_settings()}
        self.job, self.channels, self.out_channels = self.check(values)
        self.values = values
        self._checked: tuple[dict, tuple] | None = None  # the last change checked

    def check(self, values: dict) -> tuple[JobSettings, list, list]:
        """Job settings and channels of these values (ValueError naming what is wrong)."""
        for s in node_settings():  # the job's own settings are checked by JobSettings
            if s.group in ("node", "online"):
                check(s.name, values[s.name])
        if values["model_path"]:
            check_writable_file(values["model_path"], "model_path")
        channels = parse_channels(values["input_topic"], values["input_field"],
                                  values["input_type"], values["input_names"])
        out_channels = parse_channels(values["output_topic"], values["output_field"],
                                      values["output_type"], values["output_names"],
                                      role="output")
        check_roles(channels, out_channels)
        for name, topic in [("input_topic", c.topic) for c in channels] + [
                ("output_topic", c.topic) for c in out_channels]:
            self._check_topic(name, topic)
        job = JobSettings.from_values(values).for_signals(tuple(c.name for c in channels),
                                                          out_channels[0].name)
        return job, channels, out_channels

    def override(self, names: list[str], texts: list[str]) -> tuple[dict, JobSettings]:
        """The held values with a goal's overrides, checked by the schema, and their job."""
        if len(names) != len(texts):
            raise ValueError(f"{len(names)} setting_names but {len(texts)} setting_values")
        values = dict(self.values)
        for name, text in zip(names, texts):
            s = SETTINGS.get(name)
            if s is None or not s.node:
                raise ValueError(f"unknown setting {name!r} (the node's parameters: "
                                 "config/sysid_node.yaml)")
            if s.read_only:
                raise ValueError(f"{name} is set when the node starts; a goal cannot change it")
            values[name] = check(name, parse_text(s, text))
        return values, self.check(values)[0]

    def _check_topic(self, parameter: str, topic: str) -> None:
        """A topic name ROS accepts, or a ValueError naming the parameter."""
        from rclpy.exceptions import NameValidationException
        from rclpy.expand_topic_name import expand_topic_name
        from rclpy.validate_full_topic_name import validate_full_topic_name

        try:
            validate_full_topic_name(expand_topic_name(topic, self.node.get_name(),
                                                       self.node.get_namespace()))
        except NameValidationException as exc:
            reason = str(exc).splitlines()[0].split(": ", 1)[-1].rstrip(":")
            shown = topic if len(topic) <= 60 else f"{topic[:40]}... ({len(topic)} characters)"
            raise ValueError(f"{parameter} {shown!r} is not a valid topic name ({reason})") \
                from None

    def _check_change(self, changes) -> SetParametersResult:
        """Reject a parameter change that would make an identification impossible."""
        values = {**self.values, **{c.name: c.value for c in changes}}
        try:
            self._checked = (values, self.check(values))
        except (ValueError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _hold_change(self, changes) -> None:
        """Hold the accepted values and what was built from them while checking."""
        values = {**self.values, **{c.name: c.value for c in changes}}
        checked = self._checked
        job = checked[1][0] if checked is not None and checked[0] == values else \
            self.check(values)[0]
        self.values, self.job, self._checked = values, job, None
