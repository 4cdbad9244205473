"""Property tests of the one validation layer (:mod:`icpbench.harness.options`) and of every plugin
setting: any value of any type is taken with one meaning wherever it comes from, or refused with a
message naming where it came from and the field; never a traceback."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import settings as hyp_settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from icpbench.cli import app
from icpbench.core import registry
from icpbench.core.errors import InputError
from icpbench.harness.options import COMMANDS, LeaderboardOptions, RunOptions, TrainOptions

#: Examples drawn per (command, field) and per (plugin, setting).
FIELD_EXAMPLES, SETTING_EXAMPLES = 40, 15

_SCALARS = st.one_of(
    st.none(), st.booleans(), st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=6),
    st.sampled_from(["all", "uniform", "1,2", "0.5", "3", " , ", "1e-320", "town", "local",
                     "implicit", "", " "]))
_VALUES = st.recursive(_SCALARS, lambda inner: st.one_of(
    st.lists(inner, max_size=3),
    st.dictionaries(st.one_of(st.text(max_size=4), st.integers(0, 9)), inner, max_size=3)),
    max_leaves=6)

FIELDS = [(cmd, name) for cmd, model in COMMANDS.items() for name in model.model_fields]
SOURCE = "config file c.yaml"
#: Fields a command requires, given with every drawn value of another field.
REQUIRED = {"object-study": {"model": {"a": "a.pt"}}}


def _same(a, b) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


@pytest.mark.parametrize(("cmd", "name"), FIELDS, ids=[f"{c}.{n}" for c, n in FIELDS])
@hyp_settings(max_examples=FIELD_EXAMPLES, deadline=None, derandomize=True)
@given(value=_VALUES)
def test_any_value_of_any_field_is_taken_as_the_flag_takes_it_or_refused_naming_it(cmd, name,
                                                                                    value):
    model = COMMANDS[cmd]
    try:
        from_file = model.parse({**REQUIRED.get(cmd, {}), name: value}, SOURCE)
    except InputError as exc:
        assert SOURCE in str(exc) and f"setting {name!r}" in str(exc), str(exc)
        file_ok = False
    else:
        file_ok = True
    try:  # the same value given on the command line (or in code)
        from_flag = model.parse({**REQUIRED.get(cmd, {}), name: value})
    except InputError as exc:
        assert model.flag(name) in str(exc), str(exc)
        assert not file_ok, f"the file took {value!r} for {name}, the flag refused it: {exc}"
        return
    assert file_ok, f"the flag took {value!r} for {name}, the file refused it"
    assert _same(getattr(from_file, name), getattr(from_flag, name))


@pytest.mark.parametrize("cmd", sorted(COMMANDS))
def test_an_unknown_setting_is_refused_listing_the_valid_ones(cmd):
    with pytest.raises(InputError, match=r"c\.yaml: unknown setting\(s\) 'bogus'; valid: "):
        COMMANDS[cmd].parse({**REQUIRED.get(cmd, {}), "bogus": 1}, SOURCE)


@pytest.mark.parametrize(("model", "data", "field", "want"), [
    (RunOptions, {"budgets": "1,5"}, "budgets", [1.0, 5.0]),
    (RunOptions, {"budgets": 5}, "budgets", [5.0]),
    (RunOptions, {"seeds": "3"}, "seeds", [3]),
    (RunOptions, {"severities": [2, 2, 4]}, "severities", [2, 4]),
    (LeaderboardOptions, {"extra_attacks": "spoof, valley"}, "extra_attacks", ["spoof", "valley"]),
    (TrainOptions, {"lr": 0}, "lr", 0),
])
def test_a_value_is_read_as_its_flag_reads_it(model, data, field, want):
    assert getattr(model.parse(data), field) == want


@pytest.mark.parametrize(("model", "data", "needle"), [
    (RunOptions, {"threads": "2"}, "--threads must be an integer >= 1 and <= 1024, got '2'"),
    (RunOptions, {"strict": 1}, "--strict must be true or false, got 1"),
    (RunOptions, {"budgets": "1,1"}, "1 is given twice"),
    (RunOptions, {"budgets": [1, 1.0000001]}, "both print as λ=1"),
    (LeaderboardOptions, {"domain": "moon"}, "--domain must be one of town, unseen, got 'moon'"),
    (LeaderboardOptions, {"samples": 0}, "--samples must be an integer >= 1 or null, got 0"),
    (TrainOptions, {"max_minutes": float("inf")}, "--max-minutes must be a number > 0"),
])
def test_a_bad_value_is_refused_saying_what_it_must_be(model, data, needle):
    with pytest.raises(InputError) as exc:
        model.parse(data)
    assert needle in str(exc.value)


def test_every_command_option_help_is_its_model_description():
    """The help a user reads is the description the check uses: stated once."""
    import click
    import typer.main

    group = typer.main.get_command(app)
    ctx = click.Context(group)
    for cmd, model in COMMANDS.items():
        if cmd == "run":  # its options are the RunConfig fields, documented there
            continue
        command = group.get_command(ctx, cmd.split()[0])  # "run (output)": the run command
        helps = {p.name: getattr(p, "help", None) for p in command.params}
        for name in model.model_fields:
            assert helps[name] == model.help(name), (cmd, name)


# -- every plugin setting ---------------------------------------------------------------------------
def _settings() -> list[tuple[str, str, str]]:
    out = []
    for reg in (registry.attacks, registry.targets, registry.datasets, registry.monitors):
        for name in reg.names():
            if not reg.available(name)[0]:
                continue
            for key in reg.get(name).param_types():
                out.append((reg.kind, name, key))
    return out


SETTINGS = _settings()
_REGISTRIES = {"attack": registry.attacks, "target": registry.targets,
               "dataset": registry.datasets, "monitor": registry.monitors}


def test_the_plugin_settings_are_all_drawn():
    kinds = {k for k, _, _ in SETTINGS}
    assert kinds == set(_REGISTRIES) and len(SETTINGS) > 100, (kinds, len(SETTINGS))


@pytest.mark.parametrize(("kind", "name", "key"), SETTINGS,
                         ids=[f"{k}.{n}.{s}" for k, n, s in SETTINGS])
@hyp_settings(max_examples=SETTING_EXAMPLES, deadline=None, derandomize=True)
@given(value=_VALUES)
def test_any_value_of_any_plugin_setting_is_taken_or_refused_naming_it(kind, name, key, value):
    try:
        out = _REGISTRIES[kind].check_params(name, {key: value})
    except InputError as exc:
        text = str(exc)
        assert f"{kind} {name!r}" in text and key in text, text
        return
    assert set(out) == {key}


def test_help_text_in_brackets_is_shown_as_written():
    """Rich markup used to swallow ``[default: ...]`` and ``icpbench[ray]`` in ``--help``."""
    cli = CliRunner()
    board = " ".join(cli.invoke(app, ["leaderboard", "--help"]).output.split())
    assert "[default: the protocol's, 48]" in board
    run = " ".join(cli.invoke(app, ["run", "--help"]).output.split())
    assert "pip install 'icpbench[ray]'" in run
