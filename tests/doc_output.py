"""What the README and docs/ show a command print, read so that it can be held against what the command prints.

An *output block* is the lines under a ``$ command`` line of a console block (up to the next ``$`` line or the
block's end; comment lines that continue the command are not output), or a console block with no command at all (a
log excerpt). ``compare`` matches each documented line, in order, to a printed line of the same *template* (the
line with every number as ``#``, job and sweep ids as ``ID``, table borders and runs of spaces dropped: a table
laid out at another width reads the same), then compares the numbers of the two lines one by one:

* a *count* (no decimal point: steps, episodes, seeds, jobs) must be equal;
* a *figure* (a decimal: a return, a loss, a CI half-width) must agree within the block's stated tolerance;
* a number a rule names is compared with the rule's tolerance instead, or not at all (``None``: timings, pids,
  clock times). A rule is a regular expression searched in the line's template with that number written ``@``
  (``r"@ steps/s"``, ``r"^reference: .*@"``); the first rule that matches decides.

Lines a command prints that the docs leave out are allowed unless the block is compared ``whole``; a documented line
of the form ``(… text …)`` or ``…`` stands for lines left out.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

# a number standing alone, signed: 30,000 · 0.530 · −1.475 · +0.013 · 1e-5 (not the 16 of "team16", the 6 of "a78fad")
NUMBER = re.compile(r"(?<![\w.,])[-−+]?(?:\d{1,3}(?:,\d{3})+|\d+)(?:\.\d+)?(?:e[-+]?\d+)?(?![\w])")
# an id the service made up: a job's or sweep's (demo-ec0bf7, referential-a78fad-000, referential-a78fad-pop00,
# cli-861d9d), an evaluation's (cf07cb: six hex digits, one a digit at least)
ID = re.compile(r"\b(?:[a-z][a-z0-9-]*?-[0-9a-f]{6}(?:-\d{3}|-pop\d+)?|(?=[a-f]*\d)[0-9a-f]{6})\b")
BOX = re.compile(r"[│┃─━┏┓┗┛┡┩┣┫╇┳┻╋└┘┌┐├┤┬┴┼╭╮╰╯]")
ELIDED = re.compile(r"^\s*(?:…|\(….*…\))\s*$")
# a process supervisor's event ("[exited] actor-1"): processes end in any order and between any two progress lines,
# so an event is matched anywhere in the output, not in sequence
EVENT = re.compile(r"^\[(?:exited|crashed|respawned|started)\] ")

Rule = tuple[str, "float | None"]


@dataclass(frozen=True)
class Block:
    """One documented command's output (``command`` empty for a log excerpt)."""

    doc: str  # "training.md"
    line: int  # of the command (or of the excerpt's first line)
    command: str
    output: tuple[str, ...]

    @property
    def where(self) -> str:
        return f"{self.doc}:{self.line}"


def _command_end(lines: list[str], i: int) -> tuple[str, int]:
    """The command that starts at ``lines[i]`` (continued lines and quoted values that go on joined) and its last
    line's index."""
    text = lines[i][2:]
    while (text.rstrip().endswith("\\") or text.count('"') % 2) and i + 1 < len(lines):
        i += 1
        text = text.rstrip().removesuffix("\\") + " " + lines[i].strip()
    return strip_comment(text), i


def strip_comment(text: str) -> str:
    """The command without a trailing ``# comment`` (a ``#`` outside quotes, after a space)."""
    quote = None
    for i, ch in enumerate(text):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or text[i - 1] == " "):
            return text[:i].rstrip()
    return text.rstrip()


def output_blocks(docs: list[Path] = DOCS) -> list[Block]:
    """Every output block of the console blocks (```` ```console ```` or a bare fence) of ``docs``."""
    found = []
    for path in docs:
        lines = path.read_text().splitlines()
        i = 0
        while i < len(lines):
            fence = lines[i]
            i += 1
            if not fence.startswith("```"):
                continue
            kind, start = fence[3:].strip(), i
            while i < len(lines) and not lines[i].startswith("```"):
                i += 1
            body, i = lines[start:i], i + 1
            if kind != "console" and not (kind == "" and any(line.startswith("$ ") for line in body)):
                continue  # a diagram or a file, not a terminal
            j, command, at, output = 0, "", start + 1, []
            while j < len(body):
                if body[j].startswith("$ "):
                    if output:
                        found.append(Block(path.name, at, command, tuple(output)))
                    at = start + j + 1
                    command, j = _command_end(body, j)
                    output = []
                elif body[j].strip() and not body[j].lstrip().startswith("#"):  # a comment goes on the command
                    output.append(body[j])
                j += 1
            if output:
                found.append(Block(path.name, at, command, tuple(output)))
    return found


def template(line: str) -> str:
    """``line`` with ids as ``ID``, every number as ``#``, table borders and runs of spaces dropped."""
    text = NUMBER.sub("#", ID.sub("ID", line))
    return " ".join(BOX.sub(" ", text).split())


def numbers(line: str) -> list[tuple[str, float]]:
    """The numbers of ``line`` (ids left out) as (text, value): ``1,235`` → 1235, ``−1.5`` → −1.5."""
    return [(m[0], float(m[0].replace(",", "").replace("−", "-"))) for m in NUMBER.finditer(ID.sub("ID", line))]


def layout_only(line: str) -> bool:
    """A table's border or an empty line."""
    return not BOX.sub("", line).strip()


def marked(line: str, k: int) -> str:
    """``template(line)`` with its ``k``-th number as ``@`` (what a rule is matched against)."""
    text = ID.sub("ID", line)
    spans = list(NUMBER.finditer(text))
    m = spans[k]
    text = NUMBER.sub("#", text[: m.start()]) + "@" + NUMBER.sub("#", text[m.end() :])
    return " ".join(BOX.sub(" ", text).split())


# what no run reproduces: how long things took, how fast they went, clock times, process ids
TIMINGS: list[Rule] = [
    (r"@ (?:s|ms|min)\b", None),
    (r"@ (?:env )?(?:steps|upd|updates|env-steps)/s", None),
    (r"^(?:wall time|env steps/s|updates/s) @", None),
    (r"^@:#:#|^#:@:#|^#:#:@", None),  # a log line's time
    (r"pid @", None),
]


def compare(
    documented: list[str] | tuple[str, ...], printed: str, figures: float | None, rules: list[Rule] = (), whole=False
) -> list[str]:
    """What disagrees between the documented lines and the printed text (empty: they agree). ``figures``: the
    tolerance of a figure no rule names (None: not compared); ``rules`` after ``TIMINGS``; ``whole``: every
    printed line must be documented too, but where the docs leave lines out. Each documented line is matched to the
    first printed line after the previous match with its template whose numbers agree (else the first with its
    template, and the numbers that disagree are the problem)."""
    out = [line for line in printed.splitlines() if not layout_only(line)]
    events = [line.strip() for line in out if EVENT.match(line.strip())]
    out = [line for line in out if not EVENT.match(line.strip())]
    documented_events = [line.strip() for line in documented if EVENT.match(line.strip())]
    problems = [f"not printed: {e!r}" for e in documented_events if e not in events]
    if whole:
        problems += [f"printed, not documented: {e!r}" for e in events if e not in documented_events]
    at, skip = 0, False
    for line in documented:
        if layout_only(line) or EVENT.match(line.strip()):
            continue
        if ELIDED.match(line):
            skip = True
            continue
        want = template(line)
        hits = [k for k in range(at, len(out)) if template(out[k]) == want]
        if not hits:
            near = next((o for o in out[at:] if template(o)[:20] == want[:20]), None)
            problems.append(f"not printed: {line.strip()!r}" + (f"\n    printed: {near.strip()!r}" if near else ""))
            continue
        found = {k: disagreements(line, out[k], figures, rules) for k in hits}
        hit = next((k for k in hits if not found[k]), hits[0])
        if whole and not skip:
            problems += [f"printed, not documented: {o.strip()!r}" for o in out[at:hit]]
        problems += found[hit]
        at, skip = hit + 1, False
    if whole and not skip:
        problems += [f"printed, not documented: {o.strip()!r}" for o in out[at:]]
    return problems


def disagreements(line: str, got_line: str, figures: float | None, rules: list[Rule] = ()) -> list[str]:
    """The numbers of two lines of one template that disagree beyond their tolerance."""
    problems = []
    for k, ((text, doc), (got_text, got)) in enumerate(zip(numbers(line), numbers(got_line), strict=True)):
        where = marked(line, k)
        rule = next((tol for pattern, tol in [*TIMINGS, *rules] if re.search(pattern, where)), "default")
        tol = rule if rule != "default" else (figures if ("." in text or "e" in text) else 0.0)
        if tol is not None and abs(got - doc) > tol + 1e-9:
            problems.append(f"{where!r}: the docs show {text}, the command printed {got_text} (tolerance {tol:g})")
    return problems
