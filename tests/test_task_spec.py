"""Task specs load from envs/ or a path, and invalid ones fail with a message that helps."""

from __future__ import annotations

import pytest

from so101_sim.tasks import TaskSpecError, available_tasks, load_task
from so101_sim.utils.paths import envs_dir


def _write(tmp_path, old: str, new: str):
    path = tmp_path / "task.toml"
    path.write_text((envs_dir() / "pick_place.toml").read_text().replace(old, new))
    return path


def test_default_task_by_name_and_by_path():
    assert "pick_place" in available_tasks()
    by_name = load_task("pick_place")
    by_path = load_task(envs_dir() / "pick_place.toml")
    assert by_name.to_dict() | {"source": ""} == by_path.to_dict() | {"source": ""}
    assert by_name.rest_pose == (-10.374, -81.670, 77.846, 2.681, 123.209, 6.495)
    assert 0.025 <= by_name.cube_size <= 0.03


def test_unknown_task_name_lists_the_choices():
    with pytest.raises(TaskSpecError, match=r"unknown task 'pick_plaec'.*pick_place"):
        load_task("pick_plaec")


@pytest.mark.parametrize("typed, meant", [("stak", "stack"), ("pick_plac", "pick_place"),
                                          ("tidy_up", "tidy"), ("no_such_task", None)])
def test_a_misspelt_task_gets_the_one_it_is_close_to(typed: str, meant: str | None) -> None:
    with pytest.raises(TaskSpecError) as err:
        load_task(typed)
    hint = f"unknown task {typed!r} (did you mean {meant!r}?); expected one of"
    assert (hint in str(err.value)) if meant else ("did you mean" not in str(err.value))


def test_missing_task_file():
    with pytest.raises(TaskSpecError, match="does not exist"):
        load_task("/nonexistent/task.toml")


def test_a_suite_name_wins_over_a_folder_of_that_name(tmp_path, monkeypatch):
    """`record --task lift --out lift` leaves a folder `lift` here; `--task lift` is still the
    suite's task, and a folder given as a task path is named as a folder."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "lift").mkdir()
    (tmp_path / "pick_place").write_text("not toml")
    assert load_task("lift").name == "lift"
    assert load_task("pick_place").name == "pick_place"
    (tmp_path / "mine.toml").mkdir()
    with pytest.raises(TaskSpecError, match=r"'mine.toml' is a folder, not a task file"):
        load_task("mine.toml")
    with pytest.raises(TaskSpecError, match=r"'lift' is a folder"):
        load_task("./lift")


def test_unknown_key_names_key_and_allowed_keys(tmp_path):
    path = _write(tmp_path, "mass = 0.015", "colour = 'red'")
    with pytest.raises(TaskSpecError, match=r"unknown key 'cube.colour'.*\['mass', 'size', 'x'"):
        load_task(path)


def test_unknown_section(tmp_path):
    path = _write(tmp_path, "[render]", "[rendering]")
    with pytest.raises(TaskSpecError, match=r"unknown section \[rendering\]"):
        load_task(path)


@pytest.mark.parametrize("old, new, said", [
    ("mass = 0.015", "mas = 0.015", "unknown key 'cube.mas' (did you mean 'mass'?); allowed"),
    ("[render]", "[rendr]", "unknown section [rendr] (did you mean 'render'?); allowed"),
    ("mass = 0.015", "colour = 'red'", "unknown key 'cube.colour'; allowed"),  # nothing near
])
def test_a_misspelt_key_or_section_in_a_task_file_gets_the_one_it_is_close_to(
        tmp_path, old: str, new: str, said: str) -> None:
    with pytest.raises(TaskSpecError) as err:
        load_task(_write(tmp_path, old, new))
    assert said in str(err.value)


@pytest.mark.parametrize("old, new, match", [
    ("fps = 30", "fps = 0", r"episode.fps = 0 is invalid; expected a positive integer"),
    ("x = [0.17, 0.25]", "x = [0.25, 0.17]", r"cube.x = \[0.25, 0.17\] is invalid; expected \[low"),
    ("shadows = false", "shadows = 'yes'", r"render.shadows = 'yes' is invalid; expected true"),
    ("size = 0.025", "size = 0.2", r"cube.size = 0.2 is invalid; expected 0.01 .. 0.05"),
    ("rest_pose = [", "rest_pose = [1.0, ", r"robot.rest_pose .* expected a list of 6 numbers"),
])
def test_invalid_values_name_key_and_expectation(tmp_path, old, new, match):
    with pytest.raises(TaskSpecError, match=match):
        load_task(_write(tmp_path, old, new))


def test_missing_required_key(tmp_path):
    with pytest.raises(TaskSpecError, match=r"missing required keys \['target.radius'\]"):
        load_task(_write(tmp_path, "radius = 0.04", ""))


def test_broken_toml(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[cube\nsize = ")
    with pytest.raises(TaskSpecError, match="not valid TOML"):
        load_task(path)
