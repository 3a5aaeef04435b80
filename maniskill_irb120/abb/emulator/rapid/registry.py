"""The builtin registry: how Python callables (an emulator's MoveL, ReadRawBytes, CRobT ...) become RAPID routines.
The calling convention (the same for procedure and function calls) is :class:`Builtins`'. See docs/rapid_subset.md,
"Built-ins from Python".
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any


@dataclass
class Builtin:
    """One registered routine; ``options`` maps lower-case option names to the Python keyword names."""

    name: str
    fn: Callable[..., Any]
    refs: frozenset[int | str] = frozenset()
    with_interp: bool = False
    options: dict[str, str] = field(default_factory=dict)
    var_keyword: bool = True

    def keyword(self, option: str) -> str | None:
        """The Python keyword for a RAPID option name, or None if the callable takes no such argument."""
        low = option.lower()
        if low in self.options:
            return self.options[low]
        return low if self.var_keyword else None


class Builtins:
    """A case-insensitive name -> :class:`Builtin` table, passed to the Interpreter (which copies its entries).

    * required RAPID arguments -> positional Python arguments, in order;
    * ``\\Opt:=value`` -> keyword argument; ``\\Switch`` -> keyword argument ``True``. Option names match the
      Python parameter names case-insensitively (``\\time`` reaches ``Time=``); with ``**kwargs`` unknown options
      arrive lower-cased;
    * arguments listed in ``refs`` (0-based positions and/or option names) arrive as a :class:`Ref` (``.value``
      reads/writes the caller's variable, array element or record component) and must be variables in RAPID;
    * other value arguments arrive as copies (float, bool, str, :class:`Record`, lists for arrays and untyped
      aggregates); non-value objects (:class:`RawBytes`, :class:`ClockVar`, :class:`Opaque`) arrive as themselves,
      so ``ReadRawBytes dev, raw`` can fill ``raw`` in place without a ref;
    * raise :class:`RapidError` ``(errno)`` to enter the RAPID ERROR handler; any other exception is fatal;
    * ``with_interp=True`` passes the :class:`Interpreter` first (clock, logs, module data, ``errno``, and
      ``host``, the controller running the task); that parameter is no RAPID option."""

    def __init__(self, entries: Mapping[str, Callable[..., Any]] | None = None):
        self._table: dict[str, Builtin] = {}
        for name, fn in (entries or {}).items():
            self.add(name, fn)

    def add(
        self, name: str, fn: Callable[..., Any], *, refs: Iterable[int | str] = (), with_interp: bool = False
    ) -> Builtin:
        """Register ``fn`` as RAPID routine ``name`` (replacing any earlier one of that name)."""
        options, var_keyword = {}, True
        try:
            params = list(inspect.signature(fn).parameters.values())[1 if with_interp else 0 :]  # not the interpreter
            var_keyword = any(p.kind is p.VAR_KEYWORD for p in params)
            options = {p.name.lower(): p.name for p in params if p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD)}
        except (TypeError, ValueError):  # no signature (C callables): pass options through lower-cased
            pass
        refs = frozenset(r.lower() if isinstance(r, str) else r for r in refs)
        entry = Builtin(name, fn, refs, with_interp, options, var_keyword)
        self._table[name.lower()] = entry
        return entry

    def register(
        self, name: str | None = None, *, refs: Iterable[int | str] = (), with_interp: bool = False
    ) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
        """Decorator form of :meth:`add`; the RAPID name defaults to the function's name."""

        def deco(fn: Callable[..., Any]) -> Callable[..., Any]:
            self.add(name or fn.__name__, fn, refs=refs, with_interp=with_interp)
            return fn

        return deco

    def update(self, other: Builtins | Mapping[str, Callable[..., Any]]) -> None:
        """Add ``other``'s routines; a :class:`Builtins`' entries are copied (a shared registry stays as it is)."""
        if isinstance(other, Builtins):
            self._table.update((k, replace(b)) for k, b in other._table.items())
        else:
            for name, fn in other.items():
                self.add(name, fn)

    def get(self, name: str) -> Builtin | None:
        return self._table.get(name.lower())

    def __contains__(self, name: str) -> bool:
        return name.lower() in self._table

    def names(self) -> list[str]:
        return sorted(b.name for b in self._table.values())
