"""Timing of product calls for the benchmarks, through the interpreter's monitoring API.

:class:`CallTimer` times every call of chosen Python functions with Python's own profiling
interface (:mod:`sys.monitoring`, PEP 669): it asks for the start and the return events of
those functions' code objects only (all other code runs unobserved), so a benchmark measures a
stage of the product without touching it - no wrapper assigned, no attribute replaced, no
option in the product.

Contract:

- A target is a plain function (every call counts) or a bound method (only calls on that
  instance count; several instances of one class are told apart). Each finished call's wall
  time (``time.perf_counter``, taken after the start bookkeeping and before the return's) goes
  to ``sink(label, seconds)``; :attr:`CallTimer.totals` and :attr:`CallTimer.calls` keep the
  sums and counts per label either way.
- Calls on every thread are seen, each thread's apart; recursion nests. A call that raises is
  not counted. Generator and coroutine functions are refused (their time is not one call).
- While active a timer holds one of the monitoring tool ids (three are tried: a profiler may
  hold one); it stops watching when the ``with`` block ends, whatever happened inside.
"""

from __future__ import annotations

import inspect
import sys
import threading
import time
from collections.abc import Callable, Mapping
from types import CodeType, TracebackType

#: ``sink(label, seconds)``: called with each finished call.
Sink = Callable[[str, float], None]

_MONITORING = sys.monitoring
_EVENTS = _MONITORING.events
#: Tool ids tried in order: the profiler's, then two CPython leaves unassigned.
_TOOL_IDS = (_MONITORING.PROFILER_ID, 3, 4)


def _code_and_instance(label: str, target: Callable) -> tuple[CodeType, object | None]:
    instance = getattr(target, "__self__", None)
    function = getattr(target, "__func__", target)
    code = getattr(function, "__code__", None)
    if not isinstance(code, CodeType):
        raise TypeError(
            f"{label}: a Python function or bound method is needed, got {type(target).__name__}"
        )
    if inspect.isgeneratorfunction(function) or inspect.iscoroutinefunction(function):
        raise TypeError(f"{label}: generator and coroutine functions cannot be timed per call")
    return code, instance


class CallTimer:
    """Times the calls of ``targets`` (label -> function or bound method) inside a ``with``
    block; see the module docstring."""

    def __init__(self, targets: Mapping[str, Callable], sink: Sink | None = None):
        if not targets:
            raise ValueError("CallTimer needs at least one target (label -> function)")
        self.sink = sink
        #: Seconds spent in each label's finished calls.
        self.totals: dict[str, float] = dict.fromkeys(targets, 0.0)
        #: Finished calls per label.
        self.calls: dict[str, int] = dict.fromkeys(targets, 0)
        # code -> [(instance or None, label)]: who is timed for each code object.
        self._watch: dict[CodeType, list[tuple[object | None, str]]] = {}
        for label, target in targets.items():
            code, instance = _code_and_instance(label, target)
            self._watch.setdefault(code, []).append((instance, label))
        # (thread, code) -> stack of (label or None, start): calls in progress.
        self._open: dict[tuple[int, CodeType], list[tuple[str | None, float]]] = {}
        self._tool: int | None = None

    def __enter__(self) -> CallTimer:
        for tool in _TOOL_IDS:
            if _MONITORING.get_tool(tool) is None:
                _MONITORING.use_tool_id(tool, "beavr_sim.bench")
                self._tool = tool
                break
        else:
            raise RuntimeError(
                f"no free sys.monitoring tool id among {_TOOL_IDS} (a profiler or another "
                "CallTimer is active); run the benchmark without it"
            )
        _MONITORING.register_callback(self._tool, _EVENTS.PY_START, self._start)
        _MONITORING.register_callback(self._tool, _EVENTS.PY_RETURN, self._return)
        _MONITORING.register_callback(self._tool, _EVENTS.PY_UNWIND, self._unwind)
        for code in self._watch:
            _MONITORING.set_local_events(self._tool, code, _EVENTS.PY_START | _EVENTS.PY_RETURN)
        _MONITORING.set_events(self._tool, _EVENTS.PY_UNWIND)
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        tool, self._tool = self._tool, None
        if tool is None:
            return
        _MONITORING.set_events(tool, 0)
        for code in self._watch:
            _MONITORING.set_local_events(tool, code, 0)
        for event in (_EVENTS.PY_START, _EVENTS.PY_RETURN, _EVENTS.PY_UNWIND):
            _MONITORING.register_callback(tool, event, None)
        _MONITORING.free_tool_id(tool)
        self._open.clear()

    # ------------------------------------------------------------------ callbacks
    def _start(self, code: CodeType, _offset: int) -> None:
        watchers = self._watch.get(code)
        if watchers is None:
            return
        label = None
        if len(watchers) == 1 and watchers[0][0] is None:
            label = watchers[0][1]
        else:
            this = sys._getframe(1).f_locals.get("self")
            for instance, name in watchers:
                if instance is None or instance is this:
                    label = name
                    break
        key = (threading.get_ident(), code)
        stack = self._open.get(key)
        if stack is None:
            stack = self._open[key] = []
        stack.append((label, time.perf_counter()))

    def _return(self, code: CodeType, _offset: int, _value: object) -> None:
        end = time.perf_counter()
        stack = self._open.get((threading.get_ident(), code))
        if not stack:
            return  # started before the timer did
        label, start = stack.pop()
        if label is None:
            return  # another instance's call
        seconds = end - start
        self.totals[label] += seconds
        self.calls[label] += 1
        if self.sink is not None:
            self.sink(label, seconds)

    def _unwind(self, code: CodeType, _offset: int, _exc: BaseException) -> None:
        if code in self._watch:
            stack = self._open.get((threading.get_ident(), code))
            if stack:
                stack.pop()  # a call that raised is not counted
