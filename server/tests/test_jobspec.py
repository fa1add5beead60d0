"""Job settings validation: every refusal names the field."""

import pytest

from renderfarm.jobspec import JobSettings, Limits, SettingsError, parse_settings


def test_defaults():
    assert parse_settings({}) == JobSettings()
    assert parse_settings(None) == JobSettings()


def test_spp_is_an_alias_of_max_spp_and_min_spp_follows_it_down():
    s = parse_settings({"spp": 4})
    assert s.max_spp == 4 and s.min_spp == 4
    assert parse_settings({"max_spp": 4096}).min_spp == JobSettings().min_spp
    with pytest.raises(SettingsError) as e:
        parse_settings({"spp": 4, "max_spp": 8})
    assert e.value.field == "settings.spp"


def test_numbers_given_as_strings_or_integral_floats_are_accepted():
    s = parse_settings({"width": "320", "height": 240.0, "noise_threshold": "0.05"})
    assert (s.width, s.height, s.noise_threshold) == (320, 240, 0.05)


@pytest.mark.parametrize(
    "raw,field",
    [
        ({"exposure": 1}, "settings.exposure"),
        ({"max_spp": -4}, "settings.max_spp"),
        ({"max_spp": 0}, "settings.max_spp"),
        ({"width": 0}, "settings.width"),
        ({"width": 1.5}, "settings.width"),
        ({"width": True}, "settings.width"),
        ({"height": "tall"}, "settings.height"),
        ({"sampler": "magic"}, "settings.sampler"),
        ({"integrator": 3}, "settings.integrator"),
        ({"noise_threshold": float("nan")}, "settings.noise_threshold"),
        ({"noise_threshold": -0.1}, "settings.noise_threshold"),
        ({"min_spp": 64, "max_spp": 16}, "settings.min_spp"),
        ({"time_limit_s": -1}, "settings.time_limit_s"),
        ({"tile_size": 4}, "settings.tile_size"),
        ({"seed": -1}, "settings.seed"),
        ({"max_depth": 0}, "settings.max_depth"),
    ],
)
def test_bad_settings_name_the_field(raw, field):
    with pytest.raises(SettingsError) as e:
        parse_settings(raw)
    assert e.value.field == field
    assert field.split(".")[1] in e.value.message


def test_limits_are_settings():
    limits = Limits(max_width=1000, max_spp=64)
    with pytest.raises(SettingsError, match="1..1000"):
        parse_settings({"width": 1001}, limits)
    with pytest.raises(SettingsError, match="1..64"):
        parse_settings({"max_spp": 65}, limits)
    with pytest.raises(SettingsError, match="pixels"):
        parse_settings({"width": 5000, "height": 5000}, Limits(max_pixels=10**6))
