"""What the docs tell a user is true of the code:

- every ``tools/*.py`` command (or its ``atlas-*`` console command) in the Markdown docs
  (README, CHANGELOG, ``docs/`` with the results report), the Makefile, the configs' comments
  and the tools' own docstrings names a tool that exists and only options its argument parser
  defines, and every config under ``cfgs/`` it passes exists;
- every ``pcdet_atlas/`` or ``tests/`` path the docs name exists, and every relative link of
  the Markdown docs reaches its file and heading;
- the Python examples import what exists and call it with arguments its signature takes;
- docs/attacks.md's key tables name every key the attacks accept, no other, with the defaults
  of the ``_base_`` configs.

The parsers are read by ``tool_parsers.read_parsers`` (one child process).
``tools/dev/official_waymo_metric/`` runs in its own venv (TensorFlow), so its options are read
from its source (``add_argument`` literals).
"""

from __future__ import annotations

import ast
import glob
import importlib
import inspect
import re
from pathlib import Path

import pytest
import yaml
from tool_parsers import read_parsers

from pcdet_atlas.config import REPO_ROOT
from pcdet_atlas.utils.entry_points import COMMANDS

#: configs a doc tells the reader to write before the command that uses them -> that doc
WRITTEN_BY_THE_READER = {"cfgs/atlas/msf_4f_released.yaml": "docs/getting_started.md"}
OFFICIAL_VENV = "tools/dev/official_waymo_metric/"
#: a tool by its path, or by its console command (pyproject.toml's [project.scripts])
CALL = re.compile(r"tools/[\w/]+\.py|(?<![\w/.-])atlas-[a-z]+(?:-[a-z]+)*\b")
FLAG = re.compile(r"(?<![\w-])--[A-Za-z][\w-]*")
REPO_PATH = re.compile(r"(?<![\w/.<-])cfgs/[\w./{},*-]*\.yaml")


def markdown_docs() -> list[Path]:
    """README, CHANGELOG and every Markdown file under docs/."""
    docs = [REPO_ROOT / "README.md", REPO_ROOT / "CHANGELOG.md"]
    return docs + sorted((REPO_ROOT / "docs").glob("**/*.md"))


def documented_sources() -> dict[str, str]:
    """Repository-relative name -> the text a user reads commands from."""
    paths = [*markdown_docs(), REPO_ROOT / "Makefile", *sorted(REPO_ROOT.glob("cfgs/**/*.yaml"))]
    texts = {str(p.relative_to(REPO_ROOT)): p.read_text() for p in paths}
    for path in sorted(REPO_ROOT.glob("tools/**/*.py")):
        doc = ast.get_docstring(ast.parse(path.read_text(), str(path)))
        if doc:
            texts[str(path.relative_to(REPO_ROOT))] = doc
    return texts


def invocations(text: str) -> list[tuple[str, str, int]]:
    """``(tool, its arguments, line)`` for every ``tools/*.py`` in ``text``; the arguments run to
    the end of the command (a closing backtick, the line's end, a pipe, ``&&`` or ``;``), shell
    and YAML-comment line continuations joined."""
    found = []
    for match in CALL.finditer(text):
        rest = text[match.end() :]
        joined = re.sub(r"\s*\\\n\s*(?:#\s*)?", " ", rest)
        args = re.split(r"`|\n|\s\|\s|&&|;", joined, maxsplit=1)[0]
        tool = COMMANDS.get(match.group(0), match.group(0))
        found.append((tool, args, text.count("\n", 0, match.start()) + 1))
    return found


def official_options(path: Path) -> list[str]:
    """The option strings of every ``add_argument`` call in a file, read from its source."""
    options = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "add_argument":
            options += [a.value for a in node.args if isinstance(a, ast.Constant)]
    return [o for o in options if isinstance(o, str) and o.startswith("-")]


@pytest.fixture(scope="module")
def documented_calls():
    calls = [
        (source, tool, args, line)
        for source, text in documented_sources().items()
        for tool, args, line in invocations(text)
    ]
    assert len(calls) > 150, f"found only {len(calls)} tool invocations in the docs"
    return calls


@pytest.fixture(scope="module")
def tool_options(documented_calls):
    tools = sorted({tool for _, tool, _, _ in documented_calls})
    missing = [t for t in tools if not (REPO_ROOT / t).is_file()]
    assert not missing, f"the docs name tools that do not exist: {missing}"
    ours = [t for t in tools if not t.startswith(OFFICIAL_VENV)]
    options = {tool: sorted({s for flags, _, _ in rows for s in flags})
               for tool, rows in read_parsers(ours).items()}  # fmt: skip
    unparsed = sorted(set(ours) - set(options))
    assert not unparsed, f"these tools ran to the end without parsing arguments: {unparsed}"
    for tool in set(tools) - set(ours):
        options[tool] = official_options(REPO_ROOT / tool)
    return options


def test_documented_options_exist(documented_calls, tool_options):
    wrong = [
        f"{source}:{line}: {tool} has no option {flag}"
        for source, tool, args, line in documented_calls
        for flag in FLAG.findall(args)
        if flag not in tool_options[tool]
    ]
    assert not wrong, "\n".join(wrong)
    used = {flag for _, _, args, _ in documented_calls for flag in FLAG.findall(args)}
    assert {"--cfg", "--attacks", "--fix_random_seed", "--ckpt"} <= used


def expand_braces(pattern: str) -> list[str]:
    """``a{b,c}d`` -> ``[abd, acd]`` (the shell's brace expansion; the docs nest none)."""
    match = re.search(r"\{([^{}]*)\}", pattern)
    if match is None:
        return [pattern]
    alternatives = match.group(1).split(",")
    return [
        expanded
        for alt in alternatives
        for expanded in expand_braces(pattern[: match.start()] + alt + pattern[match.end() :])
    ]


def test_documented_configs_exist(documented_calls):
    for path, doc in WRITTEN_BY_THE_READER.items():
        assert not (REPO_ROOT / path).exists(), f"{path} exists: drop it from WRITTEN_BY_THE_READER"
        assert path in (REPO_ROOT / doc).read_text(), (
            f"{doc} no longer tells the reader to write {path}"
        )
    checked, missing = 0, []
    for source, tool, args, line in documented_calls:
        for pattern in REPO_PATH.findall(args):
            for path in expand_braces(pattern):
                checked += 1
                if path not in WRITTEN_BY_THE_READER and not glob.glob(str(REPO_ROOT / path)):
                    missing.append(f"{source}:{line}: {tool} is given {path}, which does not exist")
    assert not missing, "\n".join(missing)
    assert checked > 50, f"only {checked} config paths in the documented commands"


def test_package_and_test_paths_in_the_docs_exist():
    """A file or folder of ``pcdet_atlas/`` or ``tests/`` the docs name is there (a module moved
    or renamed leaves no pointer behind)."""
    mentioned = re.compile(r"(?<![\w/.-])(?:pcdet_atlas|tests)/[\w./{},*-]*[\w*}]")
    checked, missing = 0, []
    for doc in markdown_docs():
        for pattern in mentioned.findall(doc.read_text()):
            for path in expand_braces(pattern):
                checked += 1
                if not glob.glob(str(REPO_ROOT / path)):
                    missing.append(f"{doc.relative_to(REPO_ROOT)} names {path}, which is not there")
    assert not missing, "\n".join(missing)
    assert checked > 40, checked


def strip_code(markdown: str) -> str:
    """The text outside fenced code blocks (a ``#`` line there is a comment, not a heading)."""
    return re.sub(r"^```.*?^```", "", markdown, flags=re.M | re.S)


def heading_anchors(markdown: str) -> set[str]:
    """The anchors GitHub gives a file's headings: lower case, punctuation but ``-`` and ``_``
    dropped, spaces as ``-``, a repeated heading numbered ``-1``, ``-2``, ..."""
    anchors: set[str] = set()
    for heading in re.findall(r"^#+\s+(.+?)\s*$", strip_code(markdown), flags=re.M):
        anchor = re.sub(r"[^\w\- ]", "", heading.lower()).replace(" ", "-")
        count = sum(1 for a in anchors if re.fullmatch(re.escape(anchor) + r"(-\d+)?", a))
        anchors.add(f"{anchor}-{count}" if count else anchor)
    return anchors


def test_relative_links_reach_their_file_and_heading():
    broken, checked = [], 0
    for doc in markdown_docs():
        for target in re.findall(r"\]\(([^)\s]+)\)", strip_code(doc.read_text())):
            if re.match(r"[a-z]+:", target):  # https:, mailto:
                continue
            checked += 1
            path, _, anchor = target.partition("#")
            linked = (doc.parent / path).resolve() if path else doc
            name = doc.relative_to(REPO_ROOT)
            if not linked.exists():
                broken.append(f"{name}: {target}: no such file")
            elif (
                anchor
                and linked.suffix == ".md"
                and anchor not in heading_anchors(linked.read_text())
            ):
                broken.append(f"{name}: {target}: no such heading")
    assert not broken, "\n".join(broken)
    assert checked > 80, f"only {checked} relative links in the docs"


def test_heading_anchors_follow_github():
    text = "# Model zoo\n## PHiM and PHiM+LOT: (a) `phim.yaml`\n```\n# not one\n```\n## Model zoo\n"
    assert heading_anchors(text) == {"model-zoo", "phim-and-phimlot-a-phimyaml", "model-zoo-1"}


@pytest.mark.parametrize(
    "text, expected",
    [
        ("`python tools/test.py --cfg a.yaml` then --x", " --cfg a.yaml"),
        ("python tools/train.py --cfg x \\\n    --extra_tag y\nnext --z", " --cfg x --extra_tag y"),
        ("# python tools/train.py --cfg x \\\n#     --ckpt c\n", " --cfg x --ckpt c"),
        ("tools/report.py --out d | tee log", " --out d"),
    ],
)
def test_invocations_end_where_the_command_ends(text, expected):
    assert [args for _, args, _ in invocations(text)] == [expected]


def test_a_console_command_is_read_as_its_tool():
    assert invocations("`atlas-test --cfg a.yaml`") == [("tools/test.py", " --cfg a.yaml", 1)]
    assert invocations("x\natlas-evaluate-predictions --out_dir d") == [
        ("tools/evaluate_predictions.py", " --out_dir d", 2)
    ]
    assert invocations("pcdet_atlas-x and my-atlas-y") == []


def test_options_configs_and_braces_are_read_from_a_command(tmp_path):
    calls = invocations("`python tools/test.py --cfg cfgs/atlas/nope.yaml --atacks all`")
    assert [FLAG.findall(args) for _, args, _ in calls] == [["--cfg", "--atacks"]]
    assert REPO_PATH.findall(calls[0][1]) == ["cfgs/atlas/nope.yaml"]
    assert expand_braces("cfgs/{a,b}/{c,d}.yaml") == [
        "cfgs/a/c.yaml",
        "cfgs/a/d.yaml",
        "cfgs/b/c.yaml",
        "cfgs/b/d.yaml",
    ]
    source = tmp_path / "tool.py"
    source.write_text("import argparse\nargparse.ArgumentParser().add_argument('--out', '-o')\n")
    assert official_options(source) == ["--out", "-o"]


def python_examples() -> list[tuple[str, int, str]]:
    """``(doc, line, code)`` of every fenced ``python`` block of the Markdown docs."""
    found = []
    for doc in markdown_docs():
        text = doc.read_text()
        for block in re.finditer(r"^```python\n(.*?)^```", text, flags=re.M | re.S):
            line = text.count("\n", 0, block.start()) + 2
            found.append((str(doc.relative_to(REPO_ROOT)), line, block.group(1)))
    return found


def example_errors(code: str) -> tuple[list[tuple[int, str]], int]:
    """``(line, what)`` for what in one example does not exist or does not fit: a ``from X
    import Y`` that does not resolve, or a call of an imported name whose positional count or
    keywords its signature refuses (the values are placeholders; ``*args`` / ``**kwargs`` in the
    call are not checked); and how many calls were checked."""
    tree = ast.parse(code)
    imported, errors, checked = {}, [], 0
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            module = importlib.import_module(node.module)
            for alias in node.names:
                if hasattr(module, alias.name):
                    imported[alias.asname or alias.name] = getattr(module, alias.name)
                else:
                    errors.append((node.lineno, f"{node.module} has no {alias.name}"))
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)):
            continue
        target = imported.get(node.func.id)
        if target is None or any(isinstance(a, ast.Starred) for a in node.args):
            continue
        keywords = {k.arg: None for k in node.keywords if k.arg is not None}
        checked += 1
        try:
            inspect.signature(target).bind(*[None] * len(node.args), **keywords)
        except TypeError as err:
            errors.append((node.lineno, f"{node.func.id}(...): {err}"))
    return errors, checked


def test_python_examples_fit_the_code():
    examples = python_examples()
    wrong, checked = [], 0
    for doc, first, code in examples:
        errors, calls = example_errors(code)
        wrong += [f"{doc}:{first + line - 1}: {what}" for line, what in errors]
        checked += calls
    assert not wrong, "\n".join(wrong)
    assert len(examples) >= 8 and checked >= 15, (len(examples), checked)


def test_a_wrong_import_or_keyword_in_an_example_is_found():
    code = (
        "from pcdet_atlas.config import cfg_from_yaml_file, no_such_name\n"
        "cfg = cfg_from_yaml_file('a.yaml', strict=True)\n"
        "cfg = cfg_from_yaml_file('a.yaml', 'b', 'c')\n"
        "cfg = cfg_from_yaml_file(*paths)\n"
    )
    errors, checked = example_errors(code)
    assert checked == 2, checked  # the starred call is not checked
    assert [line for line, _ in errors] == [1, 2, 3], errors
    assert errors[0][1] == "pcdet_atlas.config has no no_such_name"
    assert "'strict'" in errors[1][1] and "too many positional" in errors[2][1]


# ------------------------------------------------------------------ docs/attacks.md's key tables
def attack_key_rows() -> list[tuple[str, list[str], str, str]]:
    """``(base, keys, default, meaning)`` of every row of docs/attacks.md's config-key tables;
    ``base`` is the ``_base_`` YAML the table is about. A key without a section in a row whose
    first key has one (``INTENSITY.MAX_INTENSITY``, ``MAX_ELONGATION``) belongs to that section."""
    text = (REPO_ROOT / "docs" / "attacks.md").read_text()
    section = text[text.index("## Config keys") : text.index("\n## ", text.index("## Config keys"))]
    rows, base = [], None
    for line in section.splitlines():
        heading = re.match(r"\w+ \(`_base_/(\w+)\.yaml`\):", line)
        if heading:
            base = heading.group(1)
        elif line.startswith("| `") and base is not None:
            first, default, meaning = (c.strip() for c in line.strip().strip("|").split("|"))
            keys = re.findall(r"`([A-Z_.]+)`", first)
            prefix = keys[0].rpartition(".")[0]
            keys = [k if "." in k or not prefix else f"{prefix}.{k}" for k in keys]
            rows.append((base, keys, default, meaning))
    return rows


def attack_declarations() -> list[type]:
    """The config declaration (``CONFIG``) of every registered attack family."""
    import pcdet_atlas.attacks  # noqa: F401  (registers the classes)
    from pcdet_atlas.registry import ATTACKS

    return [cls.CONFIG for _, cls in ATTACKS.items()]


def accepted_attack_keys() -> set[str]:
    """Every key the attack families declare, dotted (``GROUND.RADIUS``)."""
    from pcdet_atlas.config_values import declared_keys

    accepted = {key for decl in attack_declarations() for key in declared_keys(decl)}
    assert any(k.startswith("TRACKING.") for k in accepted) and "BUDGET" in accepted
    return accepted


def test_every_attack_key_is_documented_and_every_documented_key_exists():
    rows = attack_key_rows()
    documented = {key for _, keys, _, _ in rows for key in keys}
    # a section documented in one row names its keys in the row's text (LIDAR)
    for _, keys, _, meaning in rows:
        documented |= {f"{keys[0]}.{k}" for k in re.findall(r"`([A-Z_]+)`", meaning)}
    accepted = accepted_attack_keys()
    sections = {key.partition(".")[0] for key in accepted | documented if "." in key}
    undocumented = sorted(k for k in accepted - documented if k not in sections)
    unknown = sorted(documented - accepted)
    assert not undocumented and not unknown, (
        f"docs/attacks.md's key tables miss {undocumented} and document keys no attack "
        f"declares: {unknown}"
    )


def test_a_key_added_to_a_declaration_must_be_documented(monkeypatch):
    """The check above reads the declarations: a new declared key fails it until documented."""
    import dataclasses

    from pcdet_atlas.attacks.removal import RemovalAttack, RemovalConfig
    from pcdet_atlas.config_values import setting

    extended = dataclasses.make_dataclass(
        "Extended", [("new_key", float, setting(1.0))], bases=(RemovalConfig,), frozen=True,
        kw_only=True,
    )  # fmt: skip
    monkeypatch.setattr(RemovalAttack, "CONFIG", extended)
    with pytest.raises(AssertionError, match="miss \\['NEW_KEY'\\]"):
        test_every_attack_key_is_documented_and_every_documented_key_exists()


def test_documented_attack_defaults_are_the_declared_defaults():
    """A documented default is the declaration's (what a YAML that leaves the key out gets); a
    required key's row shows the base config's value (checked below)."""
    from pcdet_atlas.config_values import REQUIRED, declared_settings

    declared = {}
    for decl in attack_declarations():
        declared.update({key: default for key, default, _ in declared_settings(decl)})
    checked, wrong = 0, []
    for _, keys, default, _ in attack_key_rows():
        if default in ("-", "per variant", "text"):
            continue
        cells = split_top_level(default)
        values = cells if len(cells) == len(keys) else [default] * len(keys)
        for key, text in zip(keys, values, strict=True):
            if declared.get(key, REQUIRED) is REQUIRED:
                continue  # a section (LIDAR: {}) or a required key
            value = declared[key]
            value = list(value) if isinstance(value, tuple) else value
            checked += 1
            if documented_value(text) != value:
                wrong.append(f"{key}: docs/attacks.md says {text}, the declaration {value}")
    assert not wrong, "\n".join(wrong)
    assert checked >= 30, checked


def split_top_level(text: str) -> list[str]:
    """``"[15, 20], [-3, 3]"`` -> ``["[15, 20]", "[-3, 3]"]``: commas outside brackets."""
    parts, depth, start = [], 0, 0
    for i, char in enumerate(text):
        depth += (char == "[") - (char == "]")
        if char == "," and depth == 0:
            parts.append(text[start:i].strip())
            start = i + 1
    return [*parts, text[start:].strip()]


def documented_value(text: str):
    """A default cell as a value: YAML, with numbers YAML 1.1 reads as strings (``1e4``) as
    floats."""
    value = yaml.safe_load(text.strip("`"))
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value


def test_documented_attack_defaults_are_the_base_configs():
    from pcdet_atlas.config import cfg_from_yaml_file

    checked, wrong = 0, []
    for base, keys, default, _ in attack_key_rows():
        if default in ("-", "per variant", "text"):
            continue
        cells = split_top_level(default)
        values = cells if len(cells) == len(keys) else [default] * len(keys)
        cfg = cfg_from_yaml_file(REPO_ROOT / "cfgs" / "attacks" / "_base_" / f"{base}.yaml")
        for key, text in zip(keys, values, strict=True):
            node = cfg
            for part in key.split("."):
                node = node.get(part, KeyError) if isinstance(node, dict) else KeyError
            checked += 1
            if node is KeyError:
                wrong.append(f"{key}: documented with default {text}, not in _base_/{base}.yaml")
                continue
            if documented_value(text) != node:
                wrong.append(f"{key}: docs/attacks.md says {text}, _base_/{base}.yaml has {node}")
    assert not wrong, "\n".join(wrong)
    assert checked >= 35, checked


# ------------------------------------------------- OPTIMIZATION, STAGE and ATLAS key tables
def section_key_tables() -> dict[str, dict[str, str]]:
    """``{section: {key: default}}`` of docs/getting_started.md's ``| `SECTION` key |`` tables."""
    tables: dict[str, dict[str, str]] = {}
    current = None
    for line in (REPO_ROOT / "docs" / "getting_started.md").read_text().splitlines():
        head = re.match(r"\| `([A-Z_]+)` key \| default \| meaning \|$", line)
        if head:
            current = tables.setdefault(head.group(1), {})
        elif current is not None and line.startswith("| `"):
            key, default, _ = (c.strip() for c in line.strip().strip("|").split("|"))
            current[key.strip("`")] = default
        elif not line.startswith("|"):
            current = None
    return tables


def documented_default(value) -> str:
    """A declared default as the tables write it."""
    from pcdet_atlas.config_values import REQUIRED

    if value is REQUIRED:
        return "required"
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, tuple):
        return "[" + ", ".join(documented_default(v) for v in value) + "]"
    return str(value)


def section_declarations() -> dict[str, type]:
    from pcdet_atlas.models.optimization import OptimizationConfig
    from pcdet_atlas.train_utils.atlas_eval import AtlasSection
    from pcdet_atlas.train_utils.stages import StageSection

    return {"OPTIMIZATION": OptimizationConfig, "STAGE": StageSection, "ATLAS": AtlasSection}


def check_section_tables(declarations: dict[str, type]) -> None:
    from pcdet_atlas.config_values import declared_settings

    tables = section_key_tables()
    assert set(tables) == set(declarations)
    for name, decl in declarations.items():
        declared = {key: documented_default(d) for key, d, _ in declared_settings(decl)}
        assert tables[name] == declared, f"docs/getting_started.md's {name} table"


def test_section_key_tables_are_the_declarations():
    """Each table lists exactly its section's declared keys, with the declared defaults."""
    check_section_tables(section_declarations())


def test_a_key_added_to_a_section_declaration_fails_the_table_check():
    import dataclasses

    from pcdet_atlas.config_values import setting
    from pcdet_atlas.models.optimization import OptimizationConfig

    extended = dataclasses.make_dataclass(
        "Extended", [("new_key", float, setting(1.0))], bases=(OptimizationConfig,),
        frozen=True, kw_only=True,
    )  # fmt: skip
    with pytest.raises(AssertionError, match="OPTIMIZATION table"):
        check_section_tables({**section_declarations(), "OPTIMIZATION": extended})
