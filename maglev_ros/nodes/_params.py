"""A node's parameters as data: one :class:`Param` per parameter, declared with a full
``ParameterDescriptor`` (description, type, physical range, read-only) by :func:`declare`.

A parameter with an ``apply`` function can be changed while the node runs (``ros2 param set``, or
any client of the node's ``set_parameters`` service): the new value is checked (type, range,
choices) before it is accepted and then handed to ``apply(node, value)``. A parameter without one
is read only at construction and is declared ``read_only``: a change is refused with rclpy's
reason ("Trying to set a read-only parameter: NAME."). A value out of its range or of the wrong
type is refused with a one-line reason naming the parameter; given at start (``-p``, a params
file) it raises :class:`maglev_ros.errors.UserError` instead (the node prints it and exits 1).

Floating-point parameters also take an integer (``-p stall_timeout_s:=20``) and hand out a float.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException

from maglev_ros.errors import UserError

_EXPECTED = {bool: "true or false", int: "an integer", float: "a number", str: "a string",
             list: "a list"}


@dataclass(frozen=True)
class Param:
    name: str
    default: Any                 # its type is the parameter's (a list: of its first element's type)
    description: str             # one line, with the unit
    range: tuple | None = None   # (low, high), inclusive: FloatingPointRange / IntegerRange
    choices: tuple = ()          # allowed strings
    apply: Callable[[Any, Any], None] | None = None   # (node, value) for a live change; None: read-only

    @property
    def kind(self) -> type:
        if isinstance(self.default, (list, tuple)):
            return list
        return type(self.default)

    def descriptor(self) -> ParameterDescriptor:
        d = ParameterDescriptor(name=self.name, description=self.description,
                                read_only=self.apply is None)
        if self.kind is float:
            d.dynamic_typing = True      # an integer is taken too (checked by check())
        if self.range is not None:
            lo, hi = self.range
            if self.kind is int:
                d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
            else:
                d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi),
                                                             step=0.0)]
        if self.choices:
            d.additional_constraints = "one of: " + ", ".join(self.choices)
        elif self.range is not None:
            d.additional_constraints = f"{self.range[0]:g} to {self.range[1]:g}"
        return d

    def check(self, value) -> str:
        """Why ``value`` is not acceptable ('' if it is)."""
        kind = self.kind
        if kind is float:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                return f"expected a number, got {value!r}"
            if math.isnan(float(value)):
                return "expected a number, got nan"
        elif kind is int and (isinstance(value, bool) or not isinstance(value, int)):
            return f"expected an integer, got {value!r}"
        elif kind in (bool, str) and not isinstance(value, kind):
            return f"expected a {'boolean' if kind is bool else 'string'}, got {value!r}"
        elif kind is list and not isinstance(value, (list, tuple)) and type(value).__name__ != "array":
            return f"expected a list, got {value!r}"
        if self.range is not None and kind in (int, float):
            lo, hi = self.range
            if not lo <= value <= hi:
                return f"expected {lo:g} to {hi:g}, got {value!r}"
        if self.choices and value not in self.choices:
            return f"expected one of {', '.join(self.choices)}, got {value!r}"
        return ""

    def value(self, raw):
        return float(raw) if self.kind is float else (list(raw) if self.kind is list else raw)


class _Registry:
    """The node's Param table and its two callbacks (added once per node)."""

    def __init__(self, node) -> None:
        self.node = node
        self.specs: dict[str, Param] = {}
        self.declaring = False
        node.add_on_set_parameters_callback(self.validate)
        node.add_post_set_parameters_callback(self.applied)

    def validate(self, params) -> SetParametersResult:
        for p in params:
            spec = self.specs.get(p.name)
            if spec is None:
                continue                    # rclpy's own (use_sim_time, qos_overrides.*)
            why = spec.check(p.value)
            if why:
                return SetParametersResult(successful=False, reason=f"parameter '{p.name}': {why}")
        return SetParametersResult(successful=True)

    def applied(self, params) -> None:
        if self.declaring:
            return                          # the node reads its start values from declare()
        for p in params:
            spec = self.specs.get(p.name)
            if spec is not None and spec.apply is not None:
                spec.apply(self.node, spec.value(p.value))


def declare(node, params) -> dict:
    """Declare ``params`` (Param, ...) on ``node``; returns {name: start value} (floats as float).

    Raises UserError naming the parameter when a start value (``-p``, params file) is invalid."""
    reg = getattr(node, "_maglev_params", None)
    if reg is None:
        reg = node._maglev_params = _Registry(node)
    out = {}
    reg.declaring = True
    try:
        for spec in params:
            reg.specs[spec.name] = spec
            default = list(spec.default) if spec.kind is list else spec.default
            try:
                if spec.kind is list and not default:
                    raise ValueError(f"{spec.name}: an empty default gives no type")
                raw = node.declare_parameter(spec.name, default, spec.descriptor()).value
            except InvalidParameterValueException as exc:
                # our own check's reason (or rclpy's range check's), without rclpy's preamble
                reason = str(exc).split("Reason: ", 1)[-1].splitlines()[0].removesuffix(f": {spec.name}")
                raise UserError(_one_line(spec, reason)) from None
            except InvalidParameterTypeException:
                raise UserError(f"parameter '{spec.name}': expected {_EXPECTED[spec.kind]} "
                                f"({spec.description})") from None
            why = spec.check(raw)
            if why:
                raise UserError(f"parameter '{spec.name}': {why}")
            out[spec.name] = spec.value(raw)
    finally:
        reg.declaring = False
    return out


def _one_line(spec: Param, reason: str) -> str:
    reason = reason.strip().rstrip(".")
    prefix = f"parameter '{spec.name}': "
    return reason if reason.startswith(prefix) else prefix + reason
