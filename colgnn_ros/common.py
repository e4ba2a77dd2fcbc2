"""What the colgnn_ros nodes share: QoS profiles, parameters, and the process shell.

- QoS (docs/ARCHITECTURE.md, "Real-time path"): tool poses are best-effort with depth 1 (only the newest
  pose matters, a late pose is worthless); outputs (markers, counts, diagnostics) are reliable, as
  RViz subscribes to markers.
- Parameters are described once as :class:`ParamSpec` rows, declared with rcl_interfaces
  descriptors (ranges, read-only, a description each) by :func:`declare_parameters`, and the same
  rows print the ``--help`` text. A bad value raises :class:`colgnn_core.errors.InputError`.
- Transport: :func:`run_node` points Fast DDS at :data:`FASTDDS_PROFILE` (shared memory that holds a
  whole mesh Marker, plus UDP) unless the user chose a profile file or another RMW; see
  :func:`use_large_data_transport`.
- :func:`run_node` is the ``main`` of a node process: it initialises rclpy, builds the node, spins
  it until the node reports it is done or SIGINT/SIGTERM arrives, and returns the exit code
  (0 = finished or stopped by a signal, 2 = bad parameters, with one error line naming the problem).

Signals: the node process handles SIGINT and SIGTERM itself (``rclpy.init`` with
``SignalHandlerOptions.NO``). The handler raises :class:`ShutdownRequested` in the main thread, and sets a
flag that :func:`spin` checks in case Python swallows the exception (in a ``__del__``, say); the executor is spun in
short waits (:data:`SPIN_WAIT_S`), so either happens within a fraction of a second.
:func:`run_node` then destroys the node *while the context is still valid*, and only then shuts
the context down, and returns 0. rclpy's own handlers shut the context down first, from the signal
handler; destroying a Fast DDS subscription of a node whose context is already shut down crashed
the process with SIGSEGV now and then (seen in ``make demo`` and in the installed-predictor test:
``Subscription.destroy`` under ``Node.destroy_node``). A signal that arrives while the node is being
built ends it the same way. While the node is torn down, the signals have their previous handlers
back, so a second Ctrl-C or SIGTERM still ends a teardown that hangs. Before ``run_node`` installs
its handlers (interpreter start-up and imports, well under a second) a SIGTERM ends the process the
default way.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Callable, Mapping, MutableMapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future

from colgnn_core.errors import InputError

EXIT_OK = 0
EXIT_BAD_INPUT = 2

#: Tool poses: only the newest matters; a dropped pose is replaced by the next one.
POSE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                      reliability=ReliabilityPolicy.BEST_EFFORT, durability=DurabilityPolicy.VOLATILE)
#: Markers, collision counts, diagnostics: reliable (RViz's default for markers).
OUTPUT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                        reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)

ParamValue = bool | int | float | str

_TYPES: dict[type, tuple[int, str]] = {
    bool: (ParameterType.PARAMETER_BOOL, "bool"),
    int: (ParameterType.PARAMETER_INTEGER, "integer"),
    float: (ParameterType.PARAMETER_DOUBLE, "double"),
    str: (ParameterType.PARAMETER_STRING, "string"),
}
_EXAMPLES = {bool: "true", int: "10", float: "25.0", str: "text"}
# rclpy declares these itself; a node never lists them.
_BUILTIN_PARAMETERS = ("use_sim_time",)


@dataclass(frozen=True)
class ParamSpec:
    """One node parameter: name, default (its Python type is the parameter type), description.

    ``range`` (inclusive) applies to int and float parameters; ``choices`` to strings. Parameters
    are read-only by default: the nodes read them once at start-up, so a later
    ``ros2 param set`` is refused instead of silently ignored.
    """

    name: str
    default: ParamValue
    description: str
    range: tuple[float, float] | None = None
    choices: tuple[str, ...] | None = None
    read_only: bool = True
    default_text: str | None = None  # the help's words for a default computed per scene (declare_parameters)

    @property
    def py_type(self) -> type:
        return type(self.default)  # bool before int: type(True) is bool

    @property
    def type_name(self) -> str:
        return _TYPES[self.py_type][1]

    def constraint_text(self) -> str:
        if self.choices:
            return "one of " + "|".join(self.choices)
        if self.range is not None:
            lo, hi = self.range
            return f"in [{int(lo)}, {int(hi)}]" if self.py_type is int else f"in [{lo:g}, {hi:g}]"
        return ""

    def descriptor(self) -> ParameterDescriptor:
        d = ParameterDescriptor(name=self.name, type=_TYPES[self.py_type][0], description=self.description,
                                additional_constraints=self.constraint_text(), read_only=self.read_only)
        if self.range is not None and self.py_type is float:
            d.floating_point_range = [FloatingPointRange(from_value=float(self.range[0]),
                                                         to_value=float(self.range[1]), step=0.0)]
        elif self.range is not None and self.py_type is int:
            d.integer_range = [IntegerRange(from_value=int(self.range[0]), to_value=int(self.range[1]), step=1)]
        return d


def _override_value(node: Node, name: str) -> object:
    # rclpy keeps the command-line / params-file values here; there is no public accessor.
    p = getattr(node, "_parameter_overrides", {}).get(name)
    return "?" if p is None else p.value


def declare_parameters(node: Node, specs: Sequence[ParamSpec],
                       defaults: Mapping[str, Callable[[dict[str, ParamValue]], ParamValue]] | None = None,
                       ) -> dict[str, ParamValue]:
    """Declare ``specs`` on ``node`` with descriptors; return ``{name: value}``.

    ``defaults``: for some names, the default computed from the values declared before them (in ``specs`` order),
    e.g. a scene's own setting; the declared parameter then holds what runs (``ros2 param get`` shows it). The
    computed default must have the spec's type.

    Raises InputError naming the parameter for a wrong type, a value out of range or not among the
    choices. Overrides for names the node does not declare are logged as a warning (a shared
    params file may hold other nodes' parameters), listing the valid names.
    """
    names = [s.name for s in specs]
    overrides = getattr(node, "_parameter_overrides", {})
    unknown = sorted(n for n in overrides
                     if n not in names and n not in _BUILTIN_PARAMETERS and not n.startswith("qos_overrides."))
    if unknown:
        node.get_logger().warning(f"ignoring unknown parameter(s) {', '.join(unknown)}; "
                                  f"this node's parameters: {', '.join(names)}")
    values: dict[str, ParamValue] = {}
    for s in specs:
        if defaults and s.name in defaults:
            s = replace(s, default=s.py_type(defaults[s.name](values)))
        try:
            value = node.declare_parameter(s.name, s.default, s.descriptor()).value
        except InvalidParameterTypeException:
            got = _override_value(node, s.name)
            raise InputError(f"parameter {s.name!r} must be a {s.type_name} (e.g. {s.name}:={_EXAMPLES[s.py_type]}), "
                             f"got {got!r} ({type(got).__name__})") from None
        except InvalidParameterValueException:
            raise InputError(f"parameter {s.name!r} must be {s.constraint_text()}, "
                             f"got {_override_value(node, s.name)!r}") from None
        if s.choices and value not in s.choices:
            raise InputError(f"parameter {s.name!r} must be {s.constraint_text()}, got {value!r}")
        values[s.name] = value
    return values


def format_help(prog: str, summary: str, specs: Sequence[ParamSpec]) -> str:
    """The ``--help`` text: usage, summary and one line per parameter."""
    lines = [f"usage: {prog} [--ros-args -p NAME:=VALUE ...]", "", summary, "", "parameters:"]
    for s in specs:
        extra = s.constraint_text()
        default = s.default_text or repr(s.default)
        lines.append(f"  {s.name} ({s.type_name}, default {default}{'; ' + extra if extra else ''})")
        lines.append(f"      {s.description}")
    return "\n".join(lines)


SPIN_WAIT_S = 0.1
"""Longest executor wait (s): how long a signal may wait for the main thread to run Python again."""


#: The Fast DDS profile of the node processes (the file's comment gives the measurement behind it).
FASTDDS_PROFILE = Path(__file__).with_name("fastdds_large_data.xml")
#: Environment variables by which Fast DDS (2.x, 3.x) reads a profile file; a user's choice wins.
FASTDDS_PROFILE_VARIABLES = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")


def use_large_data_transport(environ: MutableMapping[str, str] = os.environ) -> str | None:
    """Make this process's Fast DDS participant publish mesh-sized messages in one piece; call before rclpy.init.

    Sets FASTRTPS_DEFAULT_PROFILES_FILE to :data:`FASTDDS_PROFILE` and returns that path, unless the user set a
    profile file (either variable) or an RMW other than Fast DDS (``RMW_IMPLEMENTATION``): then returns None and
    changes nothing. The profile keeps UDP, so subscribers on other machines still receive.
    """
    rmw = environ.get("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    if rmw not in ("rmw_fastrtps_cpp", "rmw_fastrtps_dynamic_cpp"):
        return None
    if any(environ.get(v) for v in FASTDDS_PROFILE_VARIABLES):
        return None
    environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(FASTDDS_PROFILE)
    return str(FASTDDS_PROFILE)


class ShutdownRequested(BaseException):
    """SIGINT or SIGTERM asked the node process to stop (raised by :func:`run_node`'s handler).

    A BaseException, like KeyboardInterrupt, so that a callback's "log it and go on" handler does not
    swallow it.
    """


_SHUTDOWN = threading.Event()  # set by the signal handler: the spin loop stops even if the exception is swallowed


def _request_shutdown(signum: int, _frame: object) -> None:
    # The exception stops the main thread where it is. Where Python swallows it (a signal that lands in a __del__
    # or a garbage-collection callback prints "Exception ignored" and goes on: the predictor node under load in
    # the test suite, session 14), the flag still ends spin() within SPIN_WAIT_S.
    _SHUTDOWN.set()
    raise ShutdownRequested(signal.Signals(signum).name)


def quiet_shutdown(previous: Callable[[object], object]) -> Callable[[object], None]:
    """A ``sys.unraisablehook`` that drops :class:`ShutdownRequested` and hands every other exception to ``previous``.

    Why: a signal that lands in a ``__del__`` (rclpy's ``Future.__del__`` under load) has its exception printed as
    "Exception ignored ... Traceback" on stderr, although the shutdown flag still stops :func:`spin`: a clean stop
    would read as a crash in the node's log."""

    def hook(unraisable: object) -> None:
        if not isinstance(getattr(unraisable, "exc_value", None), ShutdownRequested):
            previous(unraisable)

    return hook


def spin(node: Node, done: Future | None = None) -> None:
    """Spin ``node`` until ``done`` completes (forever if None) or its context is shut down.

    Waits at most :data:`SPIN_WAIT_S` at a time, so that a Python signal handler runs promptly.
    """
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    try:
        while node.context.ok() and (done is None or not done.done()):
            if _SHUTDOWN.is_set():
                raise ShutdownRequested("signal")
            executor.spin_once(timeout_sec=SPIN_WAIT_S)
    finally:
        executor.shutdown(timeout_sec=1.0)


def run_node(make_node: Callable[[], Node], *, prog: str, summary: str, specs: Sequence[ParamSpec],
             args: Sequence[str] | None = None) -> int:
    """Main of a node process; returns the exit code (0 done/signal, 2 bad input).

    ``make_node()`` builds the node in rclpy's default context (raising InputError for bad
    parameters); if the node has a ``done`` Future attribute, the process ends when it completes.
    ``args`` is an argv like sys.argv (program name first; the default). ``-h``/``--help`` prints
    :func:`format_help` without starting ROS; other non-ROS arguments are an error.
    """
    argv = list(sys.argv if args is None else args)
    logger = rclpy.logging.get_logger(prog)
    try:
        extra = rclpy.utilities.remove_ros_args(argv)[1:]
    except Exception as exc:  # rclpy's RCLInvalidROSArgsError, e.g. "-p name:=" without a value
        logger.error(f"bad ROS arguments: {str(exc).splitlines()[0]}")
        return EXIT_BAD_INPUT
    if any(a in ("-h", "--help") for a in extra):
        print(format_help(prog, summary, specs))
        return EXIT_OK
    if extra:
        logger.error(f"unexpected argument(s) {' '.join(extra)}; set parameters with --ros-args -p NAME:=VALUE "
                     f"(see {prog} --help)")
        return EXIT_BAD_INPUT
    profile = use_large_data_transport()
    # The default context, with our handlers instead of rclpy's (see the module docstring).
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    _SHUTDOWN.clear()
    previous = {sig: signal.signal(sig, _request_shutdown) for sig in (signal.SIGINT, signal.SIGTERM)}
    unraisable, sys.unraisablehook = sys.unraisablehook, quiet_shutdown(sys.unraisablehook)
    node: Node | None = None
    try:
        node = make_node()
        if profile is not None:
            node.get_logger().debug(f"Fast DDS profile {profile}")
        spin(node, getattr(node, "done", None))
        return EXIT_OK
    except InputError as exc:
        logger.error(str(exc))
        return EXIT_BAD_INPUT
    except (ShutdownRequested, KeyboardInterrupt, ExternalShutdownException):
        return EXIT_OK
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        sys.unraisablehook = unraisable
