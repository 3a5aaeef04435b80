"""The RAPID parser: lark LALR over grammar.lark, with syntax errors turned into :class:`RapidSyntaxError`.
See docs/rapid_subset.md.
"""

from __future__ import annotations

from functools import lru_cache
from importlib.resources import files

from lark import Lark, Tree
from lark.exceptions import UnexpectedCharacters, UnexpectedInput, UnexpectedToken

from maniskill_irb120.abb.emulator.rapid.errors import RapidSyntaxError


@lru_cache(maxsize=1)
def _parser() -> Lark:
    grammar = files("maniskill_irb120.abb.emulator.rapid").joinpath("grammar.lark").read_text()
    # the basic lexer makes keywords reserved words everywhere, as in RAPID (not just where the parser expects one)
    return Lark(grammar, parser="lalr", lexer="basic", propagate_positions=True, maybe_placeholders=True)


def parse(source: str) -> Tree:
    """The lark tree of a RAPID source; :class:`RapidSyntaxError` names line, column and what was expected."""
    parser = _parser()
    try:
        return parser.parse(source)
    except UnexpectedInput as e:
        if isinstance(e, UnexpectedToken):
            got = "end of input" if e.token.type == "$END" else repr(str(e.token))
            names = e.accepts or e.expected
        elif isinstance(e, UnexpectedCharacters):
            got, names = repr(source[e.pos_in_stream]), e.allowed
        else:
            got, names = "input", set()
        expected = sorted({_describe(parser, n) for n in names})
        more = f" (and {len(expected) - 12} more)" if len(expected) > 12 else ""
        msg = f"line {e.line}, column {e.column}: unexpected {got}; expected one of {', '.join(expected[:12])}{more}"
        raise RapidSyntaxError(msg + "\n" + e.get_context(source).rstrip(), e.line, e.column) from None


def _describe(parser: Lark, terminal: str) -> str:
    try:
        pattern = parser.get_terminal(terminal).pattern
    except KeyError:
        return terminal
    return f'"{pattern.value.upper()}"' if pattern.type == "str" else terminal
