"""MappingConfig: defaults from the paper, validation, dotted overrides, TOML."""

import dataclasses

import pytest

from gmmgp_app.config import ConfigError, MappingConfig


def test_defaults_are_auto_with_the_papers_urban_values_behind_them():
    from gmmgp_app.config import concrete

    cfg = MappingConfig()
    assert cfg.prepare.virtual_spacing == "auto" and cfg.gp.length_scale == "auto"
    urban = concrete(cfg)          # what a stage uses when it has no scan to measure
    assert urban.prepare.virtual_spacing == 0.25
    assert urban.prepare.subsample_rate == 0.15
    assert cfg.hgmm.n_children == 8
    assert cfg.hgmm.split_threshold == 0.01
    assert urban.gp.length_scale == 0.15  # ours (sweep in config.py); the authors used 0.08
    assert urban.gp.value_noise == 4e-4
    assert urban.gp.gradient_noise == 5e-4


def test_every_field_is_documented():
    for name, _default, doc in MappingConfig.describe():
        assert len(doc) > 10, f"{name} has no documentation"


def test_replace_dotted_returns_new_frozen_copy():
    cfg = MappingConfig()
    new = cfg.replace("hgmm.split_threshold", 0.02)
    assert new.hgmm.split_threshold == 0.02 and cfg.hgmm.split_threshold == 0.01
    with pytest.raises(dataclasses.FrozenInstanceError):
        new.hgmm.split_threshold = 0.5
    both = cfg.replace({"gp.d_m": 0.05, "seed": 3})
    assert both.gp.d_m == 0.05 and both.seed == 3


def test_int_accepted_for_float_field_and_float_for_int_if_integral():
    cfg = MappingConfig().replace({"gp.block_size": 1, "hgmm.n_children": 4.0})
    assert isinstance(cfg.gp.block_size, float) and cfg.gp.block_size == 1.0
    assert isinstance(cfg.hgmm.n_children, int) and cfg.hgmm.n_children == 4


@pytest.mark.parametrize("key,value,match", [
    ("hgmm.split_threshold", 0.5, r"'hgmm.split_threshold' must lie in \[0.0, 0.25\], found 0.5"),
    ("prepare.subsample_rate", 0.0, r"'prepare.subsample_rate' must lie in"),
    ("gp.length_scale", float("nan"), r"'gp.length_scale' must be finite"),
    ("hgmm.n_children", 2.5, r"'hgmm.n_children' must be an integer, found 2.5"),
    ("gp.d_m", "big", r"'gp.d_m' must be a number, found 'big'"),
    ("prepare.drop_inconsistent_virtual", 1, r"must be true or false"),
    ("hgmm.nope", 1, r"Unknown config field 'hgmm.nope'; 'hgmm' has"),
    ("nosuch.field", 1, r"Unknown config field 'nosuch.field'; expected 'section.field'"),
])
def test_validation_names_field_value_and_range(key, value, match):
    with pytest.raises(ConfigError, match=match):
        MappingConfig().replace(key, value)


def test_cli_style_overrides_parse_toml_values():
    cfg = MappingConfig().with_overrides(["hgmm.split_threshold=0.02", "surface.max_std = 0.1",
                                          "prepare.drop_inconsistent_virtual=false"])
    assert cfg.hgmm.split_threshold == 0.02 and cfg.surface.max_std == 0.1
    assert cfg.prepare.drop_inconsistent_virtual is False
    with pytest.raises(ConfigError, match="Expected an override like"):
        MappingConfig().with_overrides(["hgmm.split_threshold"])


def test_toml_round_trip(tmp_path):
    cfg = MappingConfig().replace({"hgmm.split_threshold": 0.03, "prepare.subsample_voxel": 0.1})
    path = tmp_path / "c.toml"
    path.write_text(cfg.to_toml())
    assert MappingConfig.from_toml(path) == cfg


def test_toml_errors(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        MappingConfig.from_toml(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[hgmm\nsplit_threshold = ")
    with pytest.raises(ConfigError, match="is not valid TOML"):
        MappingConfig.from_toml(bad)
    unknown = tmp_path / "unknown.toml"
    unknown.write_text("[hgmm]\nsplit_treshold = 0.02\n")
    with pytest.raises(ConfigError, match="Unknown config field 'hgmm.split_treshold'"):
        MappingConfig.from_toml(unknown)


def test_renamed_field_is_still_read_with_a_warning(tmp_path):
    from gmmgp_app.config import ConfigDeprecationWarning

    with pytest.warns(ConfigDeprecationWarning, match="'prepare.voxel_size' is now "
                                                      "'prepare.subsample_voxel'"):
        cfg = MappingConfig().replace("prepare.voxel_size", 0.2)
    assert cfg.prepare.subsample_voxel == 0.2
    path = tmp_path / "old.toml"
    path.write_text("[prepare]\nvoxel_size = 0.3\n")
    with pytest.warns(ConfigDeprecationWarning):
        assert MappingConfig.from_toml(path).prepare.subsample_voxel == 0.3
