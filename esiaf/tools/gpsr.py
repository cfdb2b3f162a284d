"""RoboCup@Home GPSR commands: the GPSRCmdGen grammar format read, commands generated with their slots.

The General Purpose Service Robot task's commands come from a grammar (``Category1Grammar.txt``
importing ``common.txt``, GPSRCmdGen's name for ``CommonRules.txt``) whose wildcards are filled from
``Names.xml``, ``Locations.xml``, ``Objects.xml`` and ``Gestures.xml``. :class:`GpsrGrammar` reads
them (the format is in ``FormatSpecification.txt``) and

- :meth:`GpsrGrammar.generate` draws a command with a seed: its text and its **slots**, the names,
  locations, objects, categories and gestures that filled the wildcards, as they are spoken;
- :meth:`GpsrGrammar.jsgf` writes the command language as a JSGF grammar for pocketsphinx;
- :meth:`GpsrGrammar.matches` says whether a text is a command of the grammar.

What of the format is handled: ``$rule = ...`` (several definitions of a rule are its alternatives,
also across files), alternatives ``|`` at the top level and in ``( ... )``, the wildcards
``{name [male|female]}``, ``{location [room|placement|beacon]}``, ``{object [known|alike|special]}``,
``{category}``, ``{gesture}``, ``{question}`` (the word "question"), ``{void}`` (nothing) and their
aliases (``{beacon}``, ``{kobject}``, ...), wildcard ids (``{name 1}`` twice is the same name; wildcards
of one kind with different ids get different values while there are enough), obfuscation (``{object?}``
says the object's category, ``{location?}`` the room, ``{category?}`` "objects"), ``{pron}`` /
``{pron sub}`` (him/her/it, he/she/it, after the last name, else the last object), metadata (``meta:``,
dropped from the text), comments (``#``, ``%``, ``;``, ``//``, ``/* */``) and the ``; load FILE`` and
``; import FILE`` directives (``import`` leaves out the file's ``$Main``).

What is not: ``where`` conditions and ``; import FILE as $rule`` (one clear error, no grammar of
2018 uses them), and a missing imported file is an error, not the ``{void}`` the format allows.
:meth:`jsgf` and :meth:`matches` are context-free: they do not tie a ``{pron}`` or an id to its
wildcard, so they accept a little more than :meth:`generate` makes (e.g. "meet Mary ... follow him").
"""
from __future__ import annotations

import random
import re
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass, field
from pathlib import Path

from esiaf.tools.robocup_scoring import normalise

ALIASES = {"beacon": ("location", "beacon"), "placement": ("location", "placement"), "room": ("location", "room"),
           "aobject": ("object", "alike"), "kobject": ("object", "known"), "sobject": ("object", "special"),
           "male": ("name", "male"), "female": ("name", "female")}
TYPES = {"name": ("male", "female"), "location": ("room", "placement", "beacon"),
         "object": ("known", "alike", "special"), "category": (), "gesture": (), "question": (), "void": (),
         "pron": ("obj", "sub")}
SLOT_KINDS = ("name", "location", "object", "category", "gesture")
FILE_ALIASES = {"common.txt": "CommonRules.txt"}  # GPSRCmdGen's resource names of the distributed files
MAX_DEPTH = 50


class GpsrError(ValueError):
    """A grammar or data file that cannot be used; the message names the file and what is wrong."""


@dataclass(frozen=True)
class Wildcard:
    kind: str  # name, location, object, category, gesture, question, void, pron
    type: str = ""  # male, room, known, sub, ...: "" for any
    id: str = ""
    obfuscated: bool = False


@dataclass(frozen=True)
class Slot:
    kind: str  # name, location, object, category, gesture
    value: str  # as spoken in the command


@dataclass
class Command:
    text: str  # as the grammar writes it (capitals, commas)
    slots: list[Slot]

    @property
    def words(self) -> str:
        """The text normalised: lower case, no punctuation (what a recogniser is scored on)."""
        return normalise(self.text)


@dataclass
class World:
    """The values of the wildcards, from the XML files."""
    names: list[tuple[str, str]] = field(default_factory=list)  # (name, male|female)
    rooms: list[str] = field(default_factory=list)
    locations: list[tuple[str, str, bool, bool]] = field(default_factory=list)  # (name, room, placement, beacon)
    objects: list[tuple[str, str, str]] = field(default_factory=list)  # (name, category, type)
    gestures: list[str] = field(default_factory=list)

    def vocabulary(self) -> list[str]:
        """The names, places (rooms and locations), objects and object categories, each once: what a
        robot in this world should expect to hear (the asr's ``vocabulary`` file, one a line)."""
        found = [n for n, _ in self.names] + self.rooms + [n for n, _, _, _ in self.locations]
        found += [n for n, _, _ in self.objects] + [c for _, c, _ in self.objects]
        return list(dict.fromkeys(found))

    def values(self, wildcard: Wildcard) -> list[tuple[str, str]]:
        """``wildcard``'s values as (value, extra): extra is a name's gender, an object's category, a
        location's room ("room" for a room), a category's obfuscation ("objects")."""
        kind, kind_type = wildcard.kind, wildcard.type
        if kind == "name":
            return [(n, g) for n, g in self.names if not kind_type or g == kind_type]
        if kind == "location":
            rooms = [(r, "room") for r in self.rooms]
            placements = [(n, room) for n, room, placement, _ in self.locations if placement]
            beacons = [(n, room) for n, room, _, beacon in self.locations if beacon]
            return {"room": rooms, "placement": placements, "beacon": beacons}.get(
                kind_type, rooms + [(n, room) for n, room, _, _ in self.locations])
        if kind == "object":
            return [(n, c) for n, c, t in self.objects if not kind_type or t == kind_type]
        if kind == "category":
            return [(c, "objects") for c in dict.fromkeys(c for _, c, _ in self.objects)]
        if kind == "gesture":
            return [(g, "") for g in self.gestures]
        return []


def _xml(path: Path) -> ElementTree.Element:
    try:
        return ElementTree.fromstring(path.read_text(encoding="utf-8-sig").strip())
    except OSError as exc:
        raise GpsrError(f"cannot read {path}: {exc.strerror or exc}") from None
    except ElementTree.ParseError as exc:
        raise GpsrError(f"{path} is not XML: {exc}") from None


def _attribute(element: ElementTree.Element, name: str, path: Path) -> str:
    value = (element.get(name) or "").strip()
    if not value:
        raise GpsrError(f"{path}: a <{element.tag}> without {name}=")
    return value


def read_world(folder: Path) -> World:
    """Names.xml, Locations.xml, Objects.xml and Gestures.xml of ``folder``."""
    world = World()
    path = folder / "Names.xml"
    for element in _xml(path).iter("name"):
        name = (element.text or "").strip()
        if not name:
            raise GpsrError(f"{path}: an empty <name>")
        world.names.append((name, (element.get("gender") or "male").strip().lower()))
    path = folder / "Locations.xml"
    for room in _xml(path).iter("room"):
        world.rooms.append(_attribute(room, "name", path))
        for location in room.iter("location"):
            world.locations.append((_attribute(location, "name", path), world.rooms[-1],
                                    location.get("isPlacement", "").lower() == "true",
                                    location.get("isBeacon", "").lower() == "true"))
    path = folder / "Objects.xml"
    for category in _xml(path).iter("category"):
        for element in category.iter("object"):
            world.objects.append((_attribute(element, "name", path), _attribute(category, "name", path),
                                  (element.get("type") or "known").strip().lower()))
    path = folder / "Gestures.xml"
    world.gestures = [_attribute(element, "name", path) for element in _xml(path).iter("gesture")]
    for what, values in (("names", world.names), ("rooms", world.rooms), ("objects", world.objects)):
        if not values:
            raise GpsrError(f"{folder}: no {what} in its XML files")
    return world


# a grammar's body: ("seq", [nodes]) | ("alt", [nodes]) | ("word", text) | ("ref", name) | ("wild", Wildcard)
Node = tuple


def _strip_comments(text: str) -> list[str]:
    text = re.sub(r"/\*.*?\*/", " ", text.lstrip("\ufeff"), flags=re.S)
    return text.splitlines()


def parse_wildcard(content: str, where: str) -> Wildcard:
    """The wildcard of ``{content}`` (its metadata dropped)."""
    content = content.split("meta:", 1)[0]
    words = content.split()
    if "where" in words:
        raise GpsrError(f"{where}: 'where' conditions are not supported ({{{content.strip()}}})")
    if not words:
        raise GpsrError(f"{where}: an empty wildcard {{}}")
    obfuscated = words[-1].endswith("?") or words[0].endswith("?")
    words = [w.rstrip("?") for w in words if w.rstrip("?")]
    kind, kind_type = words[0].lower(), ""
    if kind in ALIASES:
        kind, kind_type = ALIASES[kind]
    if kind not in TYPES:
        raise GpsrError(f"{where}: unknown wildcard {{{content.strip()}}}")
    ident = ""
    for word in words[1:]:
        if word.lower() in TYPES[kind] and not kind_type:
            kind_type = word.lower()
        elif word.isdigit() and not ident:
            ident = word
        # other words: types the format says are ignored (e.g. {category 1 type})
    return Wildcard(kind, kind_type, ident, obfuscated)


_TOKEN = re.compile(r"\s*(?:(\$\w+)|([()|])|(\{)|([^\s(){}|$]+))")


def _closing_brace(text: str, position: int, where: str) -> int:
    """Where the wildcard opened before ``position`` ends (after its ``}``; wildcards nest in metadata)."""
    depth, end = 1, position
    while depth and end < len(text):
        depth += {"{": 1, "}": -1}.get(text[end], 0)
        end += 1
    if depth:
        raise GpsrError(f"{where}: a '{{' without its '}}'")
    return end


def parse_body(text: str, where: str) -> Node:
    """A rule's right-hand side as a tree."""
    position = 0
    stack: list[list[list[Node]]] = [[[]]]  # open groups; a group is a list of alternatives (lists of nodes)
    while position < len(text.rstrip()):
        match = _TOKEN.match(text, position)
        if match is None:
            raise GpsrError(f"{where}: cannot read {text[position:].strip()!r}")
        reference, mark, brace, word = match.groups()
        position = match.end()
        if reference:
            stack[-1][-1].append(("ref", reference[1:]))
        elif word:
            stack[-1][-1].append(("word", word))
        elif brace:
            end = _closing_brace(text, position, where)
            stack[-1][-1].append(("wild", parse_wildcard(text[position:end - 1], where)))
            position = end
        elif mark == "(":
            stack.append([[]])
        elif mark == "|":
            stack[-1].append([])
        elif mark == ")":
            if len(stack) == 1:
                raise GpsrError(f"{where}: a ')' without its '('")
            group = stack.pop()
            stack[-1][-1].append(("alt", [("seq", seq) for seq in group]))
    if len(stack) != 1:
        raise GpsrError(f"{where}: a '(' without its ')'")
    return ("alt", [("seq", seq) for seq in stack[0]])


class GpsrGrammar:
    """A GPSR grammar file (with what it imports) and the world its wildcards draw from."""

    def __init__(self, grammar: Path, world: World | None = None) -> None:
        self.path = Path(grammar)
        self.rules: dict[str, list[Node]] = {}
        self._read(self.path, main=True, seen=())
        if "Main" not in self.rules:
            raise GpsrError(f"{self.path}: no $Main rule")
        self._check(("ref", "Main"), (), self.path)
        self.world = world if world is not None else read_world(self.path.parent)
        self._regex: re.Pattern[str] | None = None

    def _read(self, path: Path, main: bool, seen: tuple[Path, ...]) -> None:
        if path.resolve() in seen:
            raise GpsrError(f"{path} imports itself")
        try:
            lines = _strip_comments(path.read_text(encoding="utf-8-sig"))
        except OSError as exc:
            raise GpsrError(f"cannot read grammar {path}: {exc.strerror or exc}") from None
        except UnicodeDecodeError:
            raise GpsrError(f"grammar {path} is not UTF-8 text") from None
        for number, line in enumerate(lines, 1):
            where = f"{path.name}:{number}"
            directive = re.match(r"\s*;\s*(load|import)\s+(.+?)\s*$", line)
            if directive:
                target = directive.group(2).strip('"')
                if re.search(r"\sas\s+\$", target):
                    raise GpsrError(f"{where}: '; import FILE as $rule' is not supported")
                found = path.parent / target
                if not found.is_file() and target in FILE_ALIASES:
                    found = path.parent / FILE_ALIASES[target]
                if not found.is_file():
                    raise GpsrError(f"{where}: the imported grammar {target} is not in {path.parent}")
                self._read(found, main=directive.group(1) == "load", seen=(*seen, path.resolve()))
                continue
            line = re.split(r"//|[#%;]", line, maxsplit=1)[0].strip()
            if not line:
                continue
            rule = re.match(r"\$(\w+)\s*=(.*)$", line)
            if rule is None:
                raise GpsrError(f"{where}: not a rule ($name = ...): {line[:60]!r}")
            if rule.group(1) == "Main" and not main:
                continue
            self.rules.setdefault(rule.group(1), []).append(parse_body(rule.group(2), where))

    def _check(self, node: Node, path: tuple[str, ...], where: Path) -> None:
        """Every rule reachable from $Main defined, none recursive (the language is finite)."""
        kind, value = node
        if kind in ("seq", "alt"):
            for child in value:
                self._check(child, path, where)
        elif kind == "ref":
            if value in path:
                raise GpsrError(f"{where}: ${value} refers to itself ({' -> '.join('$' + p for p in path)})")
            if value not in self.rules:
                raise GpsrError(f"{where}: ${value} is used but not defined" + (
                    f" (in ${path[-1]})" if path else ""))
            for body in self.rules[value]:
                self._check(body, (*path, value), where)

    # generation

    def generate(self, rng: random.Random) -> Command:
        """A random command: a $Main alternative and each of its choices uniformly at random."""
        state: dict = {"fixed": {}, "used": {}, "slots": [], "last": []}
        words = self._expand(("ref", "Main"), rng, state)
        text = " ".join(words).replace(" ,", ",")
        text = re.sub(r"\s+", " ", text).strip()
        return Command(text[:1].upper() + text[1:], state["slots"])

    def _expand(self, node: Node, rng: random.Random, state: dict) -> list[str]:
        kind, value = node
        if kind == "word":
            return [value]
        if kind == "seq":
            return [word for child in value for word in self._expand(child, rng, state)]
        if kind == "alt":
            return self._expand(rng.choice(value), rng, state)
        if kind == "ref":
            return self._expand(rng.choice(self.rules[value]), rng, state)
        return self._fill(value, rng, state)

    def _fill(self, wildcard: Wildcard, rng: random.Random, state: dict) -> list[str]:
        if wildcard.kind == "void":
            return []
        if wildcard.kind == "question":
            return ["question"]
        if wildcard.kind == "pron":
            gender = next((extra for kind, extra in reversed(state["last"]) if kind == "name"), None)
            if gender is None:
                return ["it"]
            objective = wildcard.type != "sub"
            return [{"male": "him" if objective else "he", "female": "her" if objective else "she"}.get(gender, "it")]
        key = (wildcard.kind, wildcard.type, wildcard.id)
        if wildcard.id and key in state["fixed"]:
            value, extra = state["fixed"][key]
        else:
            options = self.world.values(wildcard)
            if not options:
                raise GpsrError(f"{self.path}: no values for {{{wildcard.kind} {wildcard.type}}} in the XML files")
            used = state["used"].setdefault(wildcard.kind, set())
            fresh = [option for option in options if option[0] not in used] or options
            value, extra = rng.choice(fresh)
            used.add(value)
            if wildcard.id:
                state["fixed"][key] = (value, extra)
        state["last"].append((wildcard.kind, extra))
        if wildcard.obfuscated and wildcard.kind in ("object", "location", "category"):
            spoken = extra if wildcard.kind != "location" or wildcard.type != "room" else "room"
            kind = {"object": "category", "location": "location", "category": ""}[wildcard.kind]
        else:
            spoken, kind = value, wildcard.kind
        if kind in SLOT_KINDS:
            state["slots"].append(Slot(kind, spoken))
        return spoken.split()

    # the language, for recognisers

    def _choices(self, wildcard: Wildcard) -> list[str]:
        """What ``wildcard`` can be said as, normalised."""
        if wildcard.kind == "question":
            return ["question"]
        if wildcard.kind == "pron":
            return ["he", "she", "it"] if wildcard.type == "sub" else ["him", "her", "it"]
        if wildcard.kind == "void":
            return [""]
        values = self.world.values(wildcard)
        if wildcard.obfuscated and wildcard.kind in ("object", "location", "category"):
            spoken = [extra if wildcard.kind != "location" or wildcard.type != "room" else "room"
                      for _, extra in values]
        else:
            spoken = [value for value, _ in values]
        return list(dict.fromkeys(normalise(s) for s in spoken))

    def jsgf(self, name: str = "gpsr") -> str:
        """The command language as JSGF (public rule ``<command>``), words normalised."""
        rules: dict[str, str] = {}

        def expression(node: Node) -> str:
            kind, value = node
            if kind == "word":
                return normalise(value)
            if kind == "seq":
                return " ".join(part for part in (expression(child) for child in value) if part)
            if kind == "alt":
                parts = list(dict.fromkeys(expression(child) or "<NULL>" for child in value))
                return parts[0] if len(parts) == 1 else "(" + " | ".join(parts) + ")"
            if kind == "ref":
                if value not in rules:
                    rules[value] = ""
                    rules[value] = expression(("alt", self.rules[value]))
                return f"<{value}>"
            choices = self._choices(value)
            if choices == [""]:
                return ""
            rule = "_".join(("w", value.kind, value.type or "any", "obf" if value.obfuscated else "")).rstrip("_")
            rules[rule] = "(" + " | ".join(choices) + ")"
            return f"<{rule}>"

        main = expression(("ref", "Main"))
        body = "\n".join(f"<{rule}> = {text};" for rule, text in sorted(rules.items()))
        return (f"#JSGF V1.0;\n\n/* Generated by esiaf.tools.gpsr from {self.path.name}; do not edit. */\n\n"
                f"grammar {name};\n\npublic <command> = {main};\n\n{body}\n")

    def words(self) -> set[str]:
        """Every word the language uses (normalised)."""
        found: set[str] = set()

        def visit(node: Node, seen: set[str]) -> None:
            kind, value = node
            if kind == "word":
                found.update(normalise(value).split())
            elif kind in ("seq", "alt"):
                for child in value:
                    visit(child, seen)
            elif kind == "ref" and value not in seen:
                seen.add(value)
                for body in self.rules[value]:
                    visit(body, seen)
            elif kind == "wild":
                found.update(word for choice in self._choices(value) for word in choice.split())
        visit(("ref", "Main"), set())
        return found

    def matches(self, text: str) -> bool:
        """Whether ``text`` (normalised first) is a command of the grammar."""
        if self._regex is None:
            def pattern(node: Node) -> str:
                kind, value = node
                if kind == "word":
                    word = normalise(value)
                    return re.escape(word) + " " if word else ""
                if kind == "seq":
                    return "".join(pattern(child) for child in value)
                if kind == "alt":
                    return "(?:" + "|".join(pattern(child) for child in value) + ")"
                if kind == "ref":
                    return pattern(("alt", self.rules[value]))
                return "(?:" + "|".join(re.escape(c) + " " if c else "" for c in self._choices(value)) + ")"
            self._regex = re.compile(pattern(("ref", "Main")))
        return self._regex.fullmatch(normalise(text) + " ") is not None


def load(folder: Path, category: int = 1) -> GpsrGrammar:
    """The ``Category{category}Grammar.txt`` of ``folder`` (1, 2 or 3) and its world."""
    if category not in (1, 2, 3):
        raise GpsrError(f"GPSR category {category}: there are 1, 2 and 3")
    return GpsrGrammar(Path(folder) / f"Category{category}Grammar.txt")


def generate(grammar: GpsrGrammar, count: int, seed: int) -> list[Command]:
    """``count`` commands, the same for the same seed."""
    rng = random.Random(seed)
    return [grammar.generate(rng) for _ in range(count)]


def main(argv: list[str] | None = None) -> int:
    """``python -m esiaf.tools.gpsr FOLDER [--category N] [--count N] [--seed N] [--jsgf]``."""
    import argparse
    import sys
    parser = argparse.ArgumentParser(prog="python -m esiaf.tools.gpsr", description="RoboCup@Home GPSR commands")
    parser.add_argument("folder", type=Path, help="the GPSRCmdGen files (grammars and XML)")
    parser.add_argument("--category", type=int, default=1, help="grammar category, 1-3 (default 1)")
    parser.add_argument("--count", type=int, default=10, help="commands to print (default 10)")
    parser.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    parser.add_argument("--jsgf", action="store_true", help="print the command language as JSGF instead")
    args = parser.parse_args(argv)
    try:
        grammar = load(args.folder, args.category)
        if args.jsgf:
            print(grammar.jsgf(), end="")
            return 0
        for command in generate(grammar, args.count, args.seed):
            print(command.text + "\t" + "; ".join(f"{s.kind}={s.value}" for s in command.slots))
    except GpsrError as exc:
        print(f"gpsr: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
