import pytest

from eslam_core.config import ConfigError, list_presets, load_config


def write(tmp_path, text, name="c.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize("preset", ["replica", "scannet", "tum", "icl", "demo"])
def test_presets_load_with_paper_values(preset):
    cfg = load_config(preset)
    assert cfg.model.truncation == 0.06
    assert cfg.model.coarse_resolution == 0.24 and cfg.model.fine_geometry_resolution == 0.06
    assert cfg.model.fine_appearance_resolution == 0.03 and cfg.model.channels == 32
    assert cfg.mapping.weights.truncation_center == 200 and cfg.tracking.weights.free_space == 10


def test_preset_specific_values():
    tum, scannet, replica = load_config("tum"), load_config("scannet"), load_config("replica")
    assert (tum.tracking.iterations, tum.tracking.rays, tum.mapping.iterations) == (200, 5000, 60)
    assert tum.render.n_stratified == 48 and not tum.model.learn_beta
    assert (scannet.tracking.iterations, scannet.mapping.iterations) == (30, 30)
    assert (replica.render.n_stratified, replica.render.n_importance) == (32, 8)
    assert (replica.tracking.rays, replica.tracking.iterations, replica.mapping.rays) == (2000, 8, 4000)
    assert set(list_presets()) >= {"replica", "scannet", "tum", "icl", "demo"}


def test_extends_and_overrides(tmp_path):
    p = write(tmp_path, "extends: replica\ntracking: {iterations: 3}\n")
    cfg = load_config(p, {"mapping": {"rays": 100}})
    assert cfg.tracking.iterations == 3 and cfg.tracking.rays == 2000 and cfg.mapping.rays == 100
    base = write(tmp_path, "model: {truncation: 0.1}\n", "base.yaml")
    child = write(tmp_path, f"extends: {base.name}\nmodel: {{channels: 8}}\n", "child.yaml")
    cfg = load_config(child)
    assert cfg.model.truncation == 0.1 and cfg.model.channels == 8


def test_unknown_key_names_key_and_file(tmp_path):
    p = write(tmp_path, "tracking: {iteratons: 3}\n")
    with pytest.raises(ConfigError, match=r"c\.yaml.*tracking\.iteratons"):
        load_config(p)


def test_unknown_section(tmp_path):
    with pytest.raises(ConfigError, match="unknown key 'trackin'"):
        load_config(write(tmp_path, "trackin: {}\n"))


def test_wrong_type(tmp_path):
    with pytest.raises(ConfigError, match=r"c\.yaml.*'tracking\.rays' must be of type int"):
        load_config(write(tmp_path, "tracking: {rays: many}\n"))


def test_negative_truncation(tmp_path):
    with pytest.raises(ConfigError, match=r"c\.yaml.*model\.truncation.*positive"):
        load_config(write(tmp_path, "model: {truncation: -0.06}\n"))


def test_odometry_width_too_small_for_its_pyramid(tmp_path):
    with pytest.raises(ConfigError, match=r"tracking\.odometry_width.*0 \(off\) or at least 64"):
        load_config(write(tmp_path, "tracking: {odometry_width: 32}\n"))
    assert load_config("live").tracking.odometry_width == 160 and load_config("icl").tracking.odometry_width == 0
    with pytest.raises(ConfigError, match=r"tracking\.odometry_iterations.*4 positive integers"):
        load_config(write(tmp_path, "tracking: {odometry_iterations: [4, 7, 7]}\n"))


def test_fine_plane_coarser_than_coarse(tmp_path):
    with pytest.raises(ConfigError, match="fine_geometry_resolution.*coarser"):
        load_config(write(tmp_path, "model: {fine_geometry_resolution: 0.5}\n"))


def test_bad_bound_and_cycle(tmp_path):
    with pytest.raises(ConfigError, match="scene.bound"):
        load_config(write(tmp_path, "scene: {bound: [[0, 0, 0], [1, -1, 1]]}\n"))
    write(tmp_path, "extends: b.yaml\n", "a.yaml")
    write(tmp_path, "extends: a.yaml\n", "b.yaml")
    with pytest.raises(ConfigError, match="cycle"):
        load_config(tmp_path / "a.yaml")


def test_missing_file_and_unknown_preset(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")
    with pytest.raises(ConfigError, match="unknown preset 'nope'"):
        load_config("nope")


def test_a_file_that_is_not_yaml_is_one_line_with_file_line_and_column(tmp_path, capsys):
    """--config, `extends:` and the node's config_file all read through load_config: the parser's multi-line report
    becomes one ConfigError line naming file:line:column."""
    bad = write(tmp_path, "tracking:\n  iterations: 3\n  rays: 4: 5\nmapping: {}\n", "bad.yaml")
    with pytest.raises(ConfigError) as info:
        load_config(bad)
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"{bad}:3:10: ") and "not valid YAML" in message, message
    assert "fix the file" in message
    child = write(tmp_path, "extends: tab.yaml\ntracking: {iterations: 3}\n", "child.yaml")
    tab = write(tmp_path, "model:\n\ttruncation: 0.1\n", "tab.yaml")
    with pytest.raises(ConfigError, match=rf"^{tab}:2:1: not valid YAML: [^\n]*\(fix the file[^\n]*$"):
        load_config(child)

    from eslam_core.cli import main

    code = main(["run", "--config", str(bad), "--data", str(tmp_path / "none"), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and f"eslam: error: {bad}:3:" in err and "Traceback" not in err
    assert len([line for line in err.splitlines() if "YAML" in line]) == 1
