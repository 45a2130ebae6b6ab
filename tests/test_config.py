"""Config dataclasses as the one source of an option's name, type, default and help."""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass, field
from typing import Optional

import pytest

from benchmark.core.config import (add_config_arguments, config_from_dict, config_options, field_docs, option_values,
                                   overrides_from_arguments, recorded_options, with_overrides)
from benchmark.core.errors import InputError


@dataclass
class _Encoder:
    latent_dim: int = 3
    """Latent channels per level."""
    hidden: tuple[int, ...] = (256, 128)
    """Widths between the input and the latent."""


@dataclass
class _Base:
    iterations: int = 100
    """Optimisation steps."""
    encoder: _Encoder = field(default_factory=_Encoder)
    """The encoder."""


@dataclass
class _Method(_Base):
    text: Optional[str] = "background"
    """What uncovered pixels are supervised with
    (``None``: nothing)."""
    cosine: bool = True
    """Add a cosine term."""


def test_options_are_the_leaves_with_their_docstrings_and_defaults():
    options = {o.path: o for o in config_options(_Method)}
    assert list(options) == ["iterations", "encoder.latent_dim", "encoder.hidden", "text", "cosine"]
    assert options["encoder.latent_dim"].help == "Latent channels per level."
    assert options["text"].help == "What uncovered pixels are supervised with (``None``: nothing)."
    assert options["encoder.hidden"].default == (256, 128)
    assert field_docs(_Method)["iterations"] == "Optimisation steps."  # inherited from the base


def test_overrides_read_strings_by_type_and_reach_into_groups():
    cfg = with_overrides(_Method(), {"encoder.latent_dim": "5", "text": "none", "cosine": "false",
                                     "encoder.hidden": "64,32", "iterations": 7})
    assert cfg.encoder == _Encoder(5, (64, 32)) and cfg.text is None and cfg.cosine is False
    assert cfg.iterations == 7
    assert _Method().encoder.latent_dim == 3  # the default instance is untouched


def test_unknown_and_unreadable_options_are_one_line_errors():
    with pytest.raises(InputError, match="did you mean 'encoder.latent_dim'"):
        with_overrides(_Method(), {"encoder.latent_dims": "4"}, what="demo config")
    with pytest.raises(InputError, match="cannot read 'many' as int"):
        with_overrides(_Method(), {"iterations": "many"})
    with pytest.raises(InputError, match="cannot read 'maybe' as bool"):
        with_overrides(_Method(), {"cosine": "maybe"})


def test_a_config_round_trips_through_its_dict_form():
    cfg = with_overrides(_Method(), {"encoder.latent_dim": "6", "text": "none"})
    assert config_from_dict(_Method, dataclasses.asdict(cfg)) == cfg
    assert config_from_dict(_Method, {}) == _Method()
    with pytest.raises(InputError, match="unknown option 'encoder.width'"):
        config_from_dict(_Method, {"encoder": {"width": 3}})


def test_command_line_options_are_derived_with_help_and_defaults():
    parser = argparse.ArgumentParser()
    add_config_arguments(parser, _Method, title="method options")
    text = " ".join(parser.format_help().split())  # help lines wrap at the terminal width
    assert "--encoder.latent-dim" in text and "Latent channels per level. (default: 3)" in text
    assert "(default: 256,128)" in text
    args = parser.parse_args(["--encoder.latent-dim", "4", "--cosine", "no"])
    given = overrides_from_arguments(args)
    assert given == {"encoder.latent_dim": "4", "cosine": "no"}
    assert with_overrides(_Method(), given) == _Method(encoder=_Encoder(4), cosine=False)


@dataclass
class _Wide(_Encoder):
    latent_dim: int = 6
    """Latent channels (a subclass's own default and help)."""


@dataclass
class _Grouped:
    encoder: _Encoder = field(default_factory=lambda: _Encoder(latent_dim=9))
    """The encoder, nine latents by default."""
    wide: _Wide = field(default_factory=_Wide)
    """A wider encoder."""
    mode: Optional[int] = None
    """An optional count."""


def test_a_groups_options_default_to_its_default_instance_and_its_own_help():
    options = {o.path: o for o in config_options(_Grouped)}
    assert options["encoder.latent_dim"].default == 9  # the factory's instance, not the class default
    assert options["wide.latent_dim"].default == 6
    assert options["wide.latent_dim"].help == "Latent channels (a subclass's own default and help)."
    assert options["wide.hidden"].help == "Widths between the input and the latent."  # inherited


def test_option_values_and_recorded_options_read_both_record_forms():
    cfg = with_overrides(_Grouped(), {"wide.hidden": "[8, 4]", "mode": "none"})
    values = option_values(cfg)
    assert values == {"encoder.latent_dim": 9, "encoder.hidden": [256, 128], "wide.latent_dim": 6,
                      "wide.hidden": [8, 4], "mode": None}
    nested = dataclasses.asdict(cfg)
    assert recorded_options(_Grouped, nested) == {**values, "encoder.hidden": (256, 128), "wide.hidden": (8, 4)}
    flat = {"wide_hidden": [8, 4], "old_protocol_rule": "x", "mode": 3}
    assert recorded_options(_Grouped, flat, renames={"wide_hidden": "wide.hidden"}) == {"wide.hidden": (8, 4),
                                                                                       "mode": 3}
    assert recorded_options(_Grouped, None) == {}


def test_each_group_gets_its_own_help_section_and_readable_value_forms():
    parser = argparse.ArgumentParser()
    add_config_arguments(parser, _Grouped, title="demo options")
    text = " ".join(parser.format_help().split())
    assert "demo options: encoder: The encoder, nine latents by default." in text
    assert "--wide.hidden INT,..." in text and "--mode INT" in text and "(default: 9)" in text
