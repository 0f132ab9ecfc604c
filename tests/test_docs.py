"""The documentation against the code: every `tcd` command line in README.md and docs/*.md is
one that `tcd` accepts (its subcommand and options exist, its values parse), and every file of
the repository they name exists. Commands and options are renamed now and then; a reader who
copies a line from the README should not meet `unrecognized arguments`."""
import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

from tcd import cli

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

#: words that stand for a value the reader chooses (FILE.h5, N, RUN_DIR, S1,S2,...)
PLACEHOLDER = re.compile(r"^[A-Z][A-Z0-9_]*(\.[a-z0-9]+)?$|\.\.\.|[\[\]|<>]|^[A-Z][A-Z0-9_]*[,=]")


def _commands(text: str) -> list[str]:
    """The `tcd ...` command lines of a Markdown text: lines of fenced code blocks (after
    `&&`, `;` or `|`, and after VAR=value prefixes) and inline code spans that start with
    `tcd `."""
    found = []
    for block in re.findall(r"```[a-z]*\n(.*?)```", text, flags=re.S):
        for line in block.splitlines():
            line = line.split(" #", 1)[0]
            for part in re.split(r"&&|;|\s\|\s", line):
                part = re.sub(r"^\s*(\w+=\S+\s+)*", "", part).strip()
                if part.startswith("tcd "):
                    found.append(part)
    outside = re.sub(r"```.*?```", "", text, flags=re.S)
    for span in re.findall(r"`(tcd [a-z-][^`]*)`", outside):
        found += [p.strip() for p in re.split(r"&&|;", " ".join(span.split()))
                  if p.strip().startswith("tcd ")]
    return found


def _all_commands() -> list[tuple[str, str]]:
    return sorted({(doc.name, cmd) for doc in DOCS for cmd in _commands(doc.read_text())})


def _parsers_for(words: list[str]) -> list:
    """The (sub)parsers that read the options after `tcd <command> [<subcommand>]`: several
    where the text leaves the subcommand open (`tcd bench ... --json`, `tcd bench pour|shear`)."""
    import argparse
    parsers = [cli.build_parser()]
    for word in words:
        subs = [a for a in parsers[0]._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs or word.startswith("-"):
            break
        choices = subs[0].choices
        if word == "...":
            parsers = list(choices.values())
        elif all(w in choices for w in word.split("|")):
            parsers = [choices[w] for w in word.split("|")]
        else:
            break
    return parsers


def test_the_command_extractor_finds_what_it_should():
    text = ("Run `tcd run scenarios/tiny.toml --jobs 2` or\n```bash\nX=1 tcd info a.h5 | head\n"
            "tcd run s.toml && tcd figures runs/s   # comment --nope\n```\nnot tcd run here")
    assert _commands(text) == ["tcd info a.h5", "tcd run s.toml", "tcd figures runs/s",
                               "tcd run scenarios/tiny.toml --jobs 2"]


@pytest.mark.parametrize("doc, command", _all_commands(), ids=lambda v: str(v)[:80])
def test_every_tcd_command_in_the_docs_is_one_tcd_accepts(doc, command):
    words = shlex.split(command)[1:]
    parsers = _parsers_for(words)
    options = [w.split("=", 1)[0] for w in words if w.startswith("--")]
    unknown = [o for o in options if not any(o in p._option_string_actions for p in parsers)]
    assert not unknown, f"{doc}: `{command}`: {parsers[0].prog} has no option {unknown}"
    if any(PLACEHOLDER.search(w) for w in words):
        return          # a synopsis (FILE.h5, [--json], pour|shear): its options are checked
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            cli.build_parser().parse_args(cli._joined_frames(words))
            return
        except SystemExit as exc:
            if exc.code == 0:       # --version, --help
                return
    message = err.getvalue()
    # a mention of an option in the text (`tcd run --resume`, `tcd bench shear --sample`)
    # may leave out what the option or the command needs; nothing else may fail
    assert re.search(r"the following arguments are required|expected one argument", message), \
        f"{doc}: `{command}` is refused by tcd:\n{message}"


def test_the_commands_of_the_readme_are_found():
    """The check above is not vacuous: the README's main commands are among those checked."""
    readme = {cmd for doc, cmd in _all_commands() if doc == "README.md"}
    assert any(c.startswith("tcd run scenarios/") for c in readme), readme
    assert any(c.startswith("tcd bench pour --particles 2600 --time 1.0") for c in readme), readme
    assert len(_all_commands()) > 50


def test_a_renamed_option_would_be_caught():
    [parser] = _parsers_for(["bench", "pour"])
    assert "--particles" in parser._option_string_actions
    assert "--particle" not in parser._option_string_actions
    assert [p.prog for p in _parsers_for(["run", "x.toml"])] == ["tcd run"]
    assert len(_parsers_for(["bench", "pour|shear", "--json"])) == 2


REPO_PATH = re.compile(r"\b((?:benchmarks|examples|scenarios|renders|samples|tests|docs)/"
                       r"[A-Za-z0-9_./{}*-]*[A-Za-z0-9_}*])")


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_every_repository_file_the_docs_name_exists(doc):
    """A file named as benchmarks/..., examples/..., scenarios/..., renders/..., samples/...,
    tests/... or docs/... exists; a name cut short (`renders/history/scaling_session9.*`,
    `samples/leutner_seed{seed}_prepared.h5`) must begin an existing file's name. Samples a
    run regenerates (samples/regenerated/) are made by the README's commands, not shipped."""
    missing = []
    for name in sorted(set(REPO_PATH.findall(doc.read_text()))):
        if name.startswith("samples/regenerated/") and not name.endswith("README.md"):
            continue
        stem = re.split(r"[{*]", name)[0].rstrip(".")
        path = ROOT / stem
        if path.exists():
            continue
        parent = path.parent
        if not (parent.is_dir() and any(p.name.startswith(path.name) for p in parent.iterdir())):
            missing.append(name)
    assert not missing, f"{doc.name} names files that do not exist: {missing}"


def _script_commands() -> list[tuple[str, str]]:
    """`python benchmarks/X.py ...` and `python examples/X.py ...` in the docs."""
    pattern = re.compile(r"python ((?:benchmarks|examples)/[a-z_0-9]+\.py)([^`\n#]*)")
    return sorted({(doc.name, m.group(1) + m.group(2).rstrip())
                   for doc in DOCS for m in pattern.finditer(doc.read_text())})


@pytest.mark.parametrize("doc, command", _script_commands(), ids=lambda v: str(v)[:80])
def test_every_script_option_in_the_docs_is_one_the_script_declares(doc, command):
    """The scripts' options are read from their source (an `add_argument("--name"`): importing
    each would start Taichi."""
    script, *words = command.split()
    source = (ROOT / script).read_text()
    options = {w.strip("[]").split("=", 1)[0] for w in words if w.strip("[").startswith("--")}
    unknown = sorted(o for o in options if not re.search(rf"""["']{re.escape(o)}["']""", source))
    assert not unknown, f"{doc}: `python {command}`: {script} declares no option {unknown}"


def test_the_script_commands_are_found():
    found = _script_commands()
    assert any(c.startswith("examples/incline.py --theta") for _, c in found), found
    assert len(found) > 20


def test_every_scenario_key_the_docs_name_exists():
    """`[solver] bond_frame`, `[output] series_every = 10`: the section and key exist in the
    scenario schema (tcd.config), and a value given with them is one the key accepts."""
    from tcd import config
    sections = {name: field.annotation for name, field in config.Scenario.model_fields.items()
                if isinstance(field.annotation, type) and issubclass(field.annotation, config._Model)}
    mention = re.compile(r"`\[([a-z_]+)\] ([a-z_]+)(?: = ([^`]+))?`")
    checked, wrong = 0, []
    for doc in DOCS:
        for section, key, value in mention.findall(doc.read_text()):
            checked += 1
            model = sections.get(section)
            if model is None or key not in model.model_fields:
                wrong.append(f"{doc.name}: [{section}] {key}")
                continue
            if value and not PLACEHOLDER.search(value):
                import tomllib

                import pydantic
                try:
                    given = tomllib.loads(f"v = {value}")["v"]
                except tomllib.TOMLDecodeError:
                    continue        # a placeholder (`= c`)
                try:
                    model(**{key: given})
                except pydantic.ValidationError as exc:
                    # a refusal of the value itself; one that needs other keys along is not
                    own = [e["msg"] for e in exc.errors() if tuple(e["loc"]) == (key,)]
                    if own:
                        wrong.append(f"{doc.name}: [{section}] {key} = {value}: {own}")
    assert checked > 20
    assert not wrong, wrong


def test_the_readme_names_the_pythons_that_pyproject_admits():
    """The Quick start's "Python 3.11, 3.12 or 3.13" is exactly the range of
    `requires-python`, so that a reader on another Python learns it before pip does."""
    import tomllib
    spec = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["requires-python"]
    bounds = dict(re.fullmatch(r"\s*(>=|<)\s*3\.(\d+)\s*", part).groups() for part in spec.split(","))
    admitted = {f"3.{m}" for m in range(int(bounds[">="]), int(bounds["<"]))}
    readme = (ROOT / "README.md").read_text()
    sentence = re.search(r"Fresh machine, (Python [^(]*)\(", readme).group(1)
    assert set(re.findall(r"3\.\d+", sentence)) == admitted, (sentence, spec)
    import sys
    assert f"3.{sys.version_info.minor}" in admitted
