"""Config loading: typed, unknown keys rejected with a suggestion, overrides, round trip."""
import pytest

from jaxmap.config import ConfigError, MapConfig, load_config, save_config


def test_shipped_city_config_loads_and_matches_paper_defaults():
    cfg = load_config("configs/city.yaml")
    assert cfg.grid.leaf_vox_size == 0.2 and cfg.grid.feature_levels == 3 and cfg.grid.feature_dim == 8
    assert cfg.train.iters == 50 and cfg.train.nv * cfg.train.np_per_voxel == 8192
    assert cfg.sampling.label_mode == "normal"
    # the loss and its samples (N3 paper III-B): truncation tr = 0.3 m, BCE sigmoid scale beta = 0.1 m,
    # eikonal weight 0.08; near-surface offsets N(0, sigma), free samples along the whole ray
    s, t = cfg.sampling, cfg.train
    assert s.surface_sample_range_m == 0.3 and t.sigma_sigmoid_m == 0.1 and t.weight_e == 0.08
    assert s.surface_sample_n == 3 and s.free_ray_n == 6 and cfg.window.carve
    assert s.sigma_m == 0.05  # the paper's tr / 3 = 0.1 measured worse on the validation suite (docs/benchmarks.md)


def test_unknown_key_names_file_key_and_suggestion(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("train:\n  itters: 3\n")
    with pytest.raises(ConfigError) as e:
        load_config(p)
    msg = str(e.value)
    assert str(p) in msg and "train.itters" in msg and "train.iters" in msg


def test_unknown_section_is_rejected(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("trian:\n  iters: 3\n")
    with pytest.raises(ConfigError, match="did you mean 'train'"):
        load_config(p)


def test_wrong_type_is_rejected(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("train:\n  iters: many\n")
    with pytest.raises(ConfigError, match="train.iters"):
        load_config(p)


def test_overrides_apply_and_are_checked():
    cfg = load_config(None, ["train.iters=7", "sampling.label_mode=projective", "grid.leaf_vox_size=0.1"])
    assert cfg.train.iters == 7 and cfg.sampling.label_mode == "projective" and cfg.grid.leaf_vox_size == 0.1
    with pytest.raises(ConfigError, match="train.iters"):
        load_config(None, ["train.iter=7"])
    with pytest.raises(ConfigError, match="section.key=value"):
        load_config(None, ["train.iters"])


def test_missing_file_is_clear(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")


def test_resolved_config_round_trips(tmp_path):
    cfg = load_config("configs/city.yaml", ["train.iters=3"])
    save_config(cfg, tmp_path / "c.yaml")
    assert load_config(tmp_path / "c.yaml") == cfg
    assert load_config(None) == MapConfig()


def _schema(name):
    if name == "room_imt":
        from jaxmap.config import ImtConfig

        return ImtConfig
    if name in ("room_slam", "city_slam"):
        from jaxmap.config import SlamConfig

        return SlamConfig
    if name == "prior":
        from jaxmap.config import PriorConfig

        return PriorConfig
    from jaxmap.config import MapConfig

    return MapConfig


@pytest.mark.parametrize("name", ["city", "ncd", "rgbd", "room_imt", "room_slam", "city_slam", "prior"])
def test_every_shipped_config_loads_and_sets_every_key(name):
    """Each shipped config is valid and spells out every key, so it documents the full schema."""
    import dataclasses

    import yaml

    cfg = load_config(f"configs/{name}.yaml", schema=_schema(name))
    raw = yaml.safe_load(open(f"configs/{name}.yaml"))

    def keys(d, prefix=""):
        return {prefix + k if not isinstance(v, dict) else x for k, v in d.items()
                for x in (keys(v, prefix + k + ".") if isinstance(v, dict) else [prefix + k])}

    def schema_keys(c, prefix=""):
        out = set()
        for f in dataclasses.fields(c):
            v = getattr(c, f.name)
            out |= schema_keys(v, prefix + f.name + ".") if dataclasses.is_dataclass(v) else {prefix + f.name}
        return out

    assert keys(raw) == schema_keys(cfg)


def test_every_config_file_is_checked_above():
    import glob
    import os

    names = {os.path.basename(p)[:-5] for p in glob.glob("configs/*.yaml")}
    assert names == {"city", "ncd", "rgbd", "room_imt", "room_slam", "city_slam", "prior"}


def test_configs_ship_in_the_package_and_load_by_name_from_any_folder(tmp_path, monkeypatch, capsys):
    """Issue 43: the configs are package data (jaxmap/configs; the repository's configs/ links there), every
    command takes them by name from any folder, a path still works and wins over a name, and a config that
    is neither is one line naming what was given and the shipped names, whichever command it was given to."""
    import os

    from jaxmap.cli import main
    from jaxmap.config import ImtConfig, shipped_config_dir, shipped_configs

    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    assert os.path.samefile(shipped_config_dir(), os.path.join(repo, "configs"))
    assert shipped_configs() == ["city", "city_slam", "ncd", "prior", "rgbd", "room_imt", "room_slam"]
    monkeypatch.chdir(tmp_path)
    (tmp_path / "city").mkdir()  # a data folder named like a config is not a config file
    assert load_config("city") == load_config("city.yaml") == load_config(os.path.join(repo, "configs", "city.yaml"))
    assert load_config("room_imt", schema=ImtConfig).map.voxel_size_m == 0.1
    (tmp_path / "city.yaml").write_text("train:\n  iters: 7\n")  # a file of that name: the file
    assert load_config("city.yaml").train.iters == 7 and load_config("city").train.iters != 7
    with pytest.raises(ConfigError, match=r"^config not found: cty is neither a file nor a shipped config; "
                                          r"did you mean 'city'\? .*: city, city_slam, ncd, prior, rgbd"):
        load_config("cty")
    capsys.readouterr()
    for argv in (["map", "nope", "--data", "d"], ["imt", "nope", "--data", "d"], ["slam", "nope"],
                 ["prior", "eval", "nope"], ["map", "--data", "d"]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1 and "city, city_slam, ncd, prior, rgbd, room_imt, room_slam" in err, err
    assert main(["configs"]) == 0
    listed = capsys.readouterr().out
    assert "city       jaxmap map    N3 mapping" in listed and "room_imt   jaxmap imt" in listed, listed
    assert main(["configs", "room_slam"]) == 0 and "frontend:" in capsys.readouterr().out
