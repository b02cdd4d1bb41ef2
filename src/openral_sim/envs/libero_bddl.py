"""A line-aware check of a LIBERO BDDL problem file, before LIBERO's own parser sees it.

LIBERO's parser (``bddl.parsing.scan_tokens`` and ``libero...bddl_utils``) reports a missing
parenthesis without saying where, prints and skips an unknown section, and fails on an unknown
object category with a bare ``KeyError`` deep inside model loading. This module reads the file
once into groups that remember their line, and refuses the first problem it finds as a
``ROSConfigError`` naming the file and the line: unbalanced parentheses, text after the problem,
an unknown section, problem class, object category, predicate or name, a malformed region (a
range that is not four finite numbers in order, within :data:`MAX_RANGE_M`), an object placed
twice in ``(:init ...)``, and an empty goal (which LIBERO counts as met at the first step).

Pure Python: what LIBERO knows (problem classes, object categories, predicates) is passed in.
"""

from __future__ import annotations

import difflib
import math
import re
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from openral_core import ROSConfigError
from openral_core.config_files import read_config_file

SECTIONS = (
    "problem",
    ":domain",
    ":requirements",
    ":objects",
    ":obj_of_interest",
    ":fixtures",
    ":regions",
    ":scene_properties",
    ":language",
    ":init",
    ":goal",
)
"""The sections LIBERO's parser reads (it prints and ignores any other)."""

WORKSPACE_FIXTURES = ("floor", "table", "kitchen_table", "living_room_table", "study_table", "coffee_table")
"""Fixture categories the problem classes build themselves (not in LIBERO's object dictionary)."""

REGION_ATTRIBUTES = (":target", ":ranges", ":yaw_rotation", ":rgba")

MAX_RANGE_M = 100.0
"""Largest coordinate of a region's range, in metres: LIBERO's own go to about 10 m, and far-off
placements make MuJoCo's state blow up ("huge value in QPOS")."""

PLACEMENTS = ("on", "in")
"""The ``(:init ...)`` predicates that place their first argument."""

_TOKEN = re.compile(r"[()]|[^\s()]+")


@dataclass(frozen=True)
class Token:
    """One word of the file (lower-cased, as LIBERO reads it) and its 1-based line."""

    text: str
    line: int


@dataclass
class Group:
    """A parenthesised group and the line of its opening parenthesis."""

    line: int
    items: list[Token | Group] = field(default_factory=list)
    indent: int = 0

    def head(self) -> str | None:
        """The group's first word, if it starts with one."""
        first = self.items[0] if self.items else None
        return first.text if isinstance(first, Token) else None

    def groups(self) -> Iterator[Group]:
        return (item for item in self.items if isinstance(item, Group))

    def words(self) -> list[Token]:
        return [item for item in self.items if isinstance(item, Token)]


@dataclass(frozen=True)
class BddlProblem:
    """What the check learnt of a problem file."""

    problem_class: str
    language: str
    objects: dict[str, str]
    fixtures: dict[str, str]
    regions: tuple[str, ...]
    goal: tuple[tuple[str, ...], ...]


class _Refusal:
    """Builds the one-line errors of one file."""

    def __init__(self, path: Path, field: str) -> None:
        self.path = path
        self.field = field

    def __call__(self, line: int, message: str, hint: str | None = None) -> ROSConfigError:
        return ROSConfigError(f"{self.path}:{line}: {message}", field=self.field, hint=hint)


def read_groups(text: str, refuse: _Refusal) -> Group:
    """The file's one top-level group (comments after ``;`` removed, words lower-cased).

    A file whose parentheses do not balance is refused at the line the layout points to: a line
    starting with ``)`` that closes a group opened on a more indented line (a ``)`` is missing
    there), or a ``)`` in mid-line that closes a group opened on an earlier line (one too many).

    Raises:
        ROSConfigError: A ``)`` with nothing open, a ``(`` never closed, or text outside the group.
    """
    stack: list[Group] = []
    top: list[Token | Group] = []
    missing: tuple[int, int] | None = None  # (line of the '(' left open, line of the ')' that closed it instead)
    extra: tuple[int, int] | None = None  # (line of a mid-line ')', line of the '(' it closed)
    lines = text.splitlines()
    for number, raw in enumerate(lines, start=1):
        code = raw.split(";", 1)[0].lower()
        indent = len(code) - len(code.lstrip())
        for position, word in enumerate(_TOKEN.findall(code)):
            if word == "(":
                stack.append(Group(number, indent=indent))
            elif word == ")":
                if not stack:
                    raise _unbalanced(refuse, number, missing, extra, closes_nothing=True)
                done = stack.pop()
                if done.line != number:
                    if position == 0 and indent < done.indent and missing is None:
                        missing = (done.line, number)
                    if position > 0 and extra is None:
                        extra = (number, done.line)
                (stack[-1].items if stack else top).append(done)
            elif stack:
                stack[-1].items.append(Token(word, number))
            else:
                top.append(Token(word, number))
    if stack:
        raise _unbalanced(refuse, stack[-1].line, missing, extra, closes_nothing=False)
    if not top:
        raise refuse(1, "the file holds no problem", hint="write (define (problem ...) ...)")
    if len(top) > 1 or not isinstance(top[0], Group):
        stray = top[1] if isinstance(top[0], Group) else top[0]
        raise refuse(stray.line, "text outside the (define ...) group", hint="the whole problem is one group")
    return top[0]


def _unbalanced(
    refuse: _Refusal, line: int, missing: tuple[int, int] | None, extra: tuple[int, int] | None, *, closes_nothing: bool
) -> ROSConfigError:
    """The error for parentheses that do not balance, at the line the layout points to."""
    if closes_nothing:
        if extra is not None:
            return refuse(
                extra[0],
                f"one ')' too many: this line closes the '(' of line {extra[1]}, "
                f"and the ')' on line {line} closes nothing",
                hint="remove the extra ')'",
            )
        return refuse(line, "')' closes nothing", hint="remove it or add the '(' it closes")
    if missing is not None:
        return refuse(
            missing[0],
            f"a ')' is missing: this line's '(' is closed by the ')' on line {missing[1]}, which is indented less",
            hint="add the missing ')'",
        )
    return refuse(line, "this '(' is never closed", hint="add the missing ')'")


def check_bddl(
    path: Path,
    *,
    field: str,
    problem_classes: Collection[str],
    categories: Collection[str],
    predicates: Collection[str],
) -> BddlProblem:
    """Read and check a BDDL problem file against what LIBERO knows.

    Args:
        field: The scene field that named the file (errors name it).
        problem_classes: LIBERO's problem classes, lower-case (``libero_floor_manipulation``).
        categories: LIBERO's object categories (``get_object_dict()``).
        predicates: LIBERO's predicates, lower-case (``in``, ``on``, ``open``...).

    Raises:
        ROSConfigError: The file is missing or unreadable, or its first problem, with its line.
    """
    refuse = _Refusal(path, field)
    # The project's bounded reader: a FIFO does not hang, a huge or binary file is one line.
    text = read_config_file(path, field=field, missing_hint="a relative path is taken from the scene file's folder")
    root = read_groups(text, refuse)
    if root.head() != "define":
        raise refuse(root.line, "a problem file starts with (define", hint="write (define (problem NAME) ...)")
    sections: dict[str, Group] = {}
    for group in root.groups():
        name = group.head()
        if name not in SECTIONS:
            raise refuse(group.line, f"unknown section {name!r}", hint=_closest(name or "", SECTIONS))
        sections[name] = group
    problem = _problem_class(sections.get("problem"), root, refuse, problem_classes)
    objects = _typed(sections.get(":objects"), refuse, categories, what="object")
    fixtures = _typed(sections.get(":fixtures"), refuse, {*categories, *WORKSPACE_FIXTURES}, what="fixture")
    names = _Names(refuse, {*objects, *fixtures}, predicates)
    names.add_regions(sections.get(":regions"))
    if ":obj_of_interest" in sections:
        for word in sections[":obj_of_interest"].words()[1:]:
            names.check(word)
    if ":init" in sections:
        placed: dict[str, int] = {}
        for predicate in sections[":init"].groups():
            name, *arguments = names.predicate(predicate)
            if name not in PLACEMENTS or not arguments:
                continue
            if arguments[0] in placed:
                raise refuse(
                    predicate.line,
                    f"{arguments[0]!r} is placed twice: here and on line {placed[arguments[0]]}",
                    hint="keep one (On ...) or (In ...) per object in (:init ...)",
                )
            placed[arguments[0]] = predicate.line
    goal = names.goal(sections.get(":goal"), root)
    language = " ".join(t.text for t in sections[":language"].words()[1:]) if ":language" in sections else ""
    return BddlProblem(problem, language, objects, fixtures, tuple(names.regions), goal)


def _problem_class(group: Group | None, root: Group, refuse: _Refusal, problem_classes: Collection[str]) -> str:
    if group is None or len(group.words()) != 2:
        raise refuse(group.line if group else root.line, "the problem needs one class: (problem LIBERO_...)")
    name = group.words()[1]
    if name.text not in problem_classes:
        raise refuse(name.line, f"unknown problem class {name.text!r}", hint=_closest(name.text, problem_classes))
    return name.text


def _typed(group: Group | None, refuse: _Refusal, categories: Collection[str], *, what: str) -> dict[str, str]:
    """``name ... - category`` lists, each category checked."""
    typed: dict[str, str] = {}
    if group is None:
        return typed
    for nested in group.groups():
        raise refuse(nested.line, f"unexpected group in the {what} list", hint="write: name1 name2 - category")
    pending: list[Token] = []
    words = iter(group.words()[1:])
    for word in words:
        if word.text != "-":
            pending.append(word)
            continue
        category = next(words, None)
        if category is None or not pending:
            raise refuse(word.line, f"'-' needs {what} names before it and a category after it")
        if category.text not in categories:
            raise refuse(
                category.line, f"unknown {what} category {category.text!r}", hint=_closest(category.text, categories)
            )
        for name in pending:
            if name.text in typed:
                raise refuse(name.line, f"{what} {name.text!r} is declared twice")
            typed[name.text] = category.text
        pending = []
    if pending:
        name = pending[0]
        raise refuse(name.line, f"{what} {name.text!r} has no category", hint=f"write {name.text} - CATEGORY")
    return typed


class _Names:
    """The names predicates may use (objects, fixtures, regions as ``target_region``) and the checks on their use."""

    def __init__(self, refuse: _Refusal, declared: set[str], predicates: Collection[str]) -> None:
        self.refuse = refuse
        self.declared = declared
        self.predicates = predicates
        self.regions: list[str] = []
        self.orphans: dict[str, str] = {}

    def add_regions(self, group: Group | None) -> None:
        if group is None:
            return
        for region in group.groups():
            name = region.head()
            if name is None:
                raise self.refuse(region.line, "a region starts with its name")
            target = self._region_target(region, name)
            full = f"{target}_{name}"
            # LIBERO ignores a region on an undeclared target (its own files have some); using one is an error.
            if target in self.declared:
                self.regions.append(full)
            else:
                self.orphans[full] = f"region {name!r} (line {region.line}) is on {target!r}, which is not declared"

    def _region_target(self, region: Group, name: str) -> str:
        target: str | None = None
        for attribute in region.groups():
            key = attribute.head()
            if key not in REGION_ATTRIBUTES:
                hint = f"use {', '.join(REGION_ATTRIBUTES)}"
                raise self.refuse(attribute.line, f"unknown region attribute {key!r}", hint=hint)
            if key == ":target":
                words = attribute.words()
                if len(words) != 2:
                    raise self.refuse(attribute.line, "(:target NAME) names one fixture or object")
                target = words[1].text
            elif key == ":ranges":
                for box in (box for ranges in attribute.groups() for box in ranges.groups()):
                    self._range(box)
        if target is None:
            raise self.refuse(region.line, f"region {name!r} has no (:target ...)")
        return target

    def _range(self, box: Group) -> None:
        """``(x_min y_min x_max y_max)``: finite, in order, within :data:`MAX_RANGE_M`."""
        numbers = [value for value in (_number(item.text) for item in box.words()) if value is not None]
        if len(numbers) != 4 or len(box.items) != 4:
            raise self.refuse(box.line, "a range is four finite numbers: (x_min y_min x_max y_max)")
        x_min, y_min, x_max, y_max = numbers
        if max(abs(x_min), abs(y_min), abs(x_max), abs(y_max)) > MAX_RANGE_M:
            raise self.refuse(box.line, f"a range reaches beyond {MAX_RANGE_M:g} m", hint="ranges are in metres")
        if x_min > x_max or y_min > y_max:
            raise self.refuse(
                box.line,
                "a range is (x_min y_min x_max y_max), each minimum at most its maximum",
                hint=f"swap them: ({min(x_min, x_max):g} {min(y_min, y_max):g} "
                f"{max(x_min, x_max):g} {max(y_min, y_max):g})",
            )

    def check(self, word: Token) -> None:
        known = {*self.declared, *self.regions}
        if word.text in self.orphans:
            raise self.refuse(word.line, f"{word.text!r} is unusable: {self.orphans[word.text]}")
        if word.text not in known:
            raise self.refuse(word.line, f"unknown name {word.text!r}", hint=_closest(word.text, known))

    def predicate(self, group: Group) -> tuple[str, ...]:
        words = group.words()
        if not words or len(words) != len(group.items):
            raise self.refuse(group.line, "a predicate is (name arg ...), without nested groups")
        if words[0].text not in self.predicates:
            hint = _closest(words[0].text, self.predicates)
            raise self.refuse(words[0].line, f"unknown predicate {words[0].text!r}", hint=hint)
        for word in words[1:]:
            self.check(word)
        return tuple(w.text for w in words)

    def goal(self, group: Group | None, root: Group) -> tuple[tuple[str, ...], ...]:
        if group is None:
            raise self.refuse(root.line, "the problem has no (:goal ...)", hint="add the goal an episode succeeds on")
        inner = list(group.groups())
        if len(inner) != 1 or group.words()[1:]:
            raise self.refuse(group.line, "(:goal ...) holds one predicate or one (And ...)")
        body = inner[0]
        if body.head() != "and":
            return (self.predicate(body),)
        if len(body.words()) != 1:
            raise self.refuse(body.line, "(And ...) holds predicates only")
        goal = tuple(self.predicate(part) for part in body.groups())
        if not goal:
            raise self.refuse(
                body.line,
                "the goal is empty: every episode would succeed at its first step",
                hint="name what must hold, e.g. (And (In obj region))",
            )
        return goal


def _number(text: str) -> float | None:
    """``text`` as a finite number, or ``None``."""
    try:
        value = float(text)
    except ValueError:
        return None
    return value if math.isfinite(value) else None


def _closest(word: str, choices: Collection[str]) -> str:
    close = difflib.get_close_matches(word, list(choices), n=3)
    if close:
        return f"did you mean {' or '.join(repr(c) for c in close)}?"
    return f"choose from {sorted(choices)}" if len(choices) <= 12 else f"none of the {len(choices)} known is close"
