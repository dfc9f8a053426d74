import pytest

from eslam_core.config import ConfigError, config_from_dict, list_presets, load_config


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
    assert cfg.mapping.weights.truncation_center == 200 and cfg.render_tracker.weights.free_space == 10


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


def test_a_live_backlog_the_input_buffer_cannot_hold(tmp_path):
    with pytest.raises(ConfigError, match=r"runtime\.live_backlog.*below runtime\.capacity \(8\)"):
        load_config(write(tmp_path, "runtime: {live_backlog: 8}\n"))
    assert load_config("live").runtime.live_backlog == 1


def test_odometry_width_too_small_for_its_pyramid(tmp_path):
    with pytest.raises(ConfigError, match=r"odometry\.width.*0 \(off\) or at least 64"):
        load_config(write(tmp_path, "odometry: {width: 32}\n"))
    assert load_config("live").odometry.width == 160 and load_config("icl").odometry.width == 0
    with pytest.raises(ConfigError, match=r"odometry\.iterations.*4 positive integers"):
        load_config(write(tmp_path, "odometry: {iterations: [4, 7, 7]}\n"))


def test_a_key_that_moved_to_its_consumers_section_is_refused_with_its_new_name(tmp_path):
    with pytest.raises(ConfigError, match=r"'tracking\.odometry_width' is now 'odometry\.width'.*rename it"):
        load_config(write(tmp_path, "tracking: {odometry_width: 160}\n"))
    with pytest.raises(ConfigError, match=r"'tracking\.photometric_weight' is now 'sdf_tracker\.photometric_weight'"):
        load_config("fast", {"tracking": {"photometric_weight": 0.5}})


def test_a_checkpoints_config_of_the_older_layout_is_moved_not_refused():
    old = load_config("fast").to_dict()
    old["tracking"].update(odometry_width=80, color_weight=0.5, lr_rotation=0.004)
    del old["odometry"], old["sdf_tracker"], old["render_tracker"]
    cfg = config_from_dict(old, "checkpoint", migrate=True)
    assert (cfg.odometry.width, cfg.sdf_tracker.color_weight, cfg.render_tracker.lr_rotation) == (80, 0.5, 0.004)
    assert cfg.odometry.iterations == [7, 7, 7, 10]  # not in the old dict: the default
    with pytest.raises(ConfigError, match="is now"):
        config_from_dict(old, "a file")


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
