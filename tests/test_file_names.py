"""Files as people name them (issue #36): scan files given by position, overrides whose path values need
quoting said with the command that works, and the deviation view's colour range from the data."""

import json
import re
import shlex

import numpy as np
import pytest

from conftest import pkg_file, run_cli, shared
from scanreg.app.arguments import (file_overrides, path_override_error, quote_value, shell_arg, split_files,
                                   with_files)
from scanreg.errors import ConfigError
from scanreg.geometry import Cloud, apply_T, barycentric_sample, random_pose
from scanreg.io import read_mesh, write_ply, write_transform

NASTY = ["OrthoCAD_Export_1 (4)/scan #1.ply", "Pred_Upper_Mesh_Tag=0.obj", "a,b.ply", "l'arcade [haut].stl",
         "Zahnbogen oben Überbiss ß é 中.ply", "x=1,(2)/#[3]'.ply", "back\\slash.ply", "trailing\\", "both\\'s.ply"]


def _parse(override: str):
    from hydra.core.override_parser.overrides_parser import OverridesParser

    return OverridesParser.create().parse_override(override)


@pytest.mark.parametrize("name", NASTY)
def test_quoted_value_reads_back_verbatim(name):
    o = _parse(f"data.source={quote_value(name)}")
    assert not o.is_sweep_override() and o.value() == name


def test_positional_files_become_quoted_overrides(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "scans").mkdir()
    for n in ("Pred_Upper_Mesh_Tag=0.obj", "b c.ply", "scans/1.ply", "scans/2.ply"):
        (tmp_path / n).write_text("")
    # an existing file wins over the override reading of '='; flags keep their values
    files, rest = split_files(["Pred_Upper_Mesh_Tag=0.obj", "--config-dir", "confs", "b c.ply", "icp=gicp", "-m"])
    assert files == ["Pred_Upper_Mesh_Tag=0.obj", "b c.ply"]
    assert rest == ["--config-dir", "confs", "icp=gicp", "-m"]
    assert with_files(["Pred_Upper_Mesh_Tag=0.obj", "b c.ply", "icp=gicp"]) == [
        "icp=gicp", "data.source='Pred_Upper_Mesh_Tag=0.obj'", "data.target='b c.ply'"]
    # with files, Hydra's flags first, so that the overrides stay one run of arguments
    assert with_files(["b c.ply", "x.ply", "--cfg", "job", "icp=gicp", "-m"]) == [
        "--cfg", "job", "-m", "icp=gicp", "data.source='b c.ply'", "data.target='x.ply'"]
    # a folder, three files, or data=scanset: a scan set
    assert file_overrides(["scans"], []) == ["data=scanset", "data.scans='scans'"]
    assert file_overrides(["scans/1.ply", "scans/2.ply"], ["data=scanset"]) == ["data.scans=['scans/1.ply','scans/2.ply']"]
    assert file_overrides(["a", "b", "c"], []) == ["data=scanset", "data.scans=['a','b','c']"]
    # a name that is no override and no file: still a file (its reader names it missing)
    assert split_files(["missing.ply", "other.ply"])[0] == ["missing.ply", "other.ply"]
    with pytest.raises(ConfigError, match=r"one scan given \(b c.ply\)"):
        with_files(["b c.ply"])
    # one file by position, the other named as an override (quoted for its characters): the file is the other
    assert with_files(["data.source='scan (1).stl'", "ct.stl"]) == ["data.source='scan (1).stl'", "data.target='ct.stl'"]
    assert with_files(["a.ply", "data.target=b.ply"]) == ["data.target=b.ply", "data.source='a.ply'"]
    # the files and an override that names them too, or a data provider that picks its own scans: one line
    with pytest.raises(ConfigError, match=r"^data.source is given twice: by the scan files on the command line and "
                                          r"by data.source=c.ply; give one$"):
        file_overrides(["a.ply", "b.ply"], ["data.source=c.ply"])
    with pytest.raises(ConfigError, match=r"^data.scans is given twice"):
        file_overrides(["a", "b", "c"], ["+data.scans=[d]"])
    with pytest.raises(ConfigError, match=r"^scan files given \(a.ply, b.ply\) with data=stanford, which picks its own"):
        file_overrides(["a.ply", "b.ply"], ["data=stanford"])
    assert file_overrides(["a.ply", "b.ply"], ["data=files", "data.target_labels=x.json"]) == [
        "data.source='a.ply'", "data.target='b.ply'"]
    # a preset whose defaults pick a data provider that has its own scans (the command line does not show it;
    # the files were silently replaced by the benchmark's bunny pairs): one line; one that picks a scan set
    # takes the files as its scans; a preset given as a sweep is left to the run
    for experiment, data in (("bunny_benchmark", "stanford"), ("dental", "dental")):
        with pytest.raises(ConfigError, match=rf"^scan files given \(a.ply, b.ply\) with experiment={experiment}, "
                                              rf"whose data={data} picks its own scans"):
            with_files(["a.ply", "b.ply", f"experiment={experiment}", "icp=gicp,horn", "-m"])
    assert file_overrides(["a.ply", "b.ply"], ["experiment=multiview_bunny"]) == ["data.scans=['a.ply','b.ply']"]
    assert file_overrides(["a.ply", "b.ply"], ["experiment=dental,bunny_benchmark"]) == [
        "data.source='a.ply'", "data.target='b.ply'"]


def _fix_command(line: str, part: str = "value") -> list[str]:
    """The command an error line suggests: after 'quote the value:' or 'by position:'."""
    m = re.search(r"quote the values?: (scanreg .*?)(?:  \(or |$)" if part == "value" else
                  r"by position: (scanreg .*)\)$", line)
    assert m, line
    return shlex.split(m.group(1))


def test_unparsable_path_overrides_say_the_working_command():
    cases = {  # the three cases
        ("data.source=OrthoCAD_Export_1 (4)/scan #1.ply", "data.target=bun000.ply"): "'(', ')', '#'",
        ("data.source=x/Pred_Upper_Mesh_Tag=0.obj", "data.target=y.ply"): "'='",
        ("data.source=a,b.ply", "data.target=t.ply"): "','",
    }
    for argv, chars in cases.items():
        line = path_override_error(list(argv), multirun=False)
        assert line and "\n" not in line and chars in line, line
        cmd = _fix_command(line)
        assert cmd[0] == "scanreg" and cmd[2:] == [argv[1]]
        o = _parse(cmd[1])
        assert o.value() == argv[0].partition("=")[2] and not o.is_sweep_override()
        assert _fix_command(line, "position")[1:3] == [argv[0].partition("=")[2], argv[1].partition("=")[2]]
    # a sweep over such paths: each value quoted alone, so that the fix is still a sweep over both files
    line = path_override_error(["-m", "data.source=~/s/a.ply,~/s/b.ply", "data.target=t.ply"], multirun=True)
    o = _parse(_fix_command(line)[2])
    assert o.is_sweep_override() and [v.text for v in o.value().list] == ["~/s/a.ply", "~/s/b.ply"], line
    assert "holds '~', which" in line and "by position" not in line
    # what parses as meant is left alone: plain paths, quoted paths, spaces, and a sweep over files with -m
    for argv, multirun in ((["data.source=scans/a b.ply"], False), (["data.source='x (1).ply'"], False),
                           (["data.source=a.ply,b.ply"], True), (["icp=gicp", "seed=3"], False)):
        assert path_override_error(argv, multirun) is None, argv


def test_shell_arg_round_trips():
    for a in ["plain.ply", "data.source='a (4)/scan #1.ply'", 'say "hi" $HOME', "it's", "x!y", "l\\'Ü.ply",
              "end\\", "a\\$b"]:
        assert shlex.split(shell_arg(a)) == [a]


def _pair(tmp_path, src_name: str, tgt_name: str):
    """A bunny mesh as the target and a resampled, moved cloud of it as the source, under the given names."""
    m = read_mesh("pkg:pymeshfix/examples/StanfordBunny.ply")
    rng = np.random.default_rng(3)
    pts, n, _ = barycentric_sample(m, 8000, rng)
    T = random_pose(rng, 90, 10)  # T_target_source: the source is the cloud moved by its inverse
    Ti = np.linalg.inv(T)
    for name in (src_name, tgt_name):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
    write_ply(tmp_path / src_name, Cloud(apply_T(Ti, pts), n @ Ti[:3, :3].T))
    write_ply(tmp_path / tgt_name, m)
    write_transform(tmp_path / "gt.txt", T)


@pytest.mark.slow
def test_files_with_any_characters_register_positionally_and_as_quoted_overrides(tmp_path):
    src = "OrthoCAD_Export_1 (4)/scan #1, l'Überbiss [Tag=0].ply"
    tgt = "Zahnbogen oben (CT) é.ply"
    _pair(tmp_path, src, tgt)
    common = ["data.gt=gt.txt", "tracking=none", "repair=none"]
    r = run_cli([src, tgt, *common, "hydra.run.dir=positional"], tmp_path)
    assert r.returncode == 0, r.stderr
    res = json.loads((tmp_path / "positional" / "result.json").read_text())
    assert res["rotation_error_deg"] < 0.5, res["rotation_error_deg"]

    bad = run_cli([f"data.source={src}", f"data.target={tgt}", *common, "hydra.run.dir=quoted"], tmp_path)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1, bad.stderr
    cmd = _fix_command(bad.stderr.strip())
    r = run_cli(cmd[1:], tmp_path)
    assert r.returncode == 0, r.stderr
    # the same pipeline on the same files: the same transform, bit for bit
    assert (tmp_path / "quoted" / "T_target_source.txt").read_bytes() == \
        (tmp_path / "positional" / "T_target_source.txt").read_bytes()


def test_one_positional_file_is_one_line_usage_error(tmp_path):
    (tmp_path / "only one.ply").write_text("")
    r = run_cli(["only one.ply", "tracking=none"], tmp_path)
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        "error: one scan given (only one.ply): give the source and the target (scanreg SOURCE TARGET), or a folder "
        "or three or more scans to register into one model"], r.stderr
    # a mistyped folder (or file) is named missing (it said "one scan given")
    r = run_cli(["scnas", "tracking=none"], tmp_path)
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        f"error: scnas: no such file or folder ({tmp_path / 'scnas'})"], r.stderr


def test_a_shared_folder_by_position_is_a_scan_set():
    from conftest import shared

    shared("stanford_bunny")  # skips without the data
    assert file_overrides(["shared:stanford_bunny"], []) == ["data=scanset", "data.scans='shared:stanford_bunny'"]


def test_colour_range_follows_the_data():
    from scanreg.eval.deviation import colour_range
    from scanreg.eval.metrics import EvalParams

    p = EvalParams()  # mm in, µm shown
    assert colour_range(np.array([0.27, -0.1, 0.0]), p) == pytest.approx(0.3)
    for p95_um, step_um in ((0.9, 1.0), (1.2, 1.5), (33.0, 40.0), (300.0, 300.0), (7100.0, 8000.0)):
        assert colour_range(np.full(20, p95_um / 1000), p) * 1000 == pytest.approx(step_um), p95_um
    assert colour_range(np.array([np.nan]), p) == pytest.approx(0.001)  # nothing compared: one µm
    assert colour_range(np.array([0.27]), EvalParams(deviation_range=0.1)) == 0.1  # the fixed range, kept


def _figure(page: str) -> dict:
    """The page's figure: the JSON of its script element ``figure``."""
    return json.loads(re.search(r'<script id="figure" type="application/json">(.*?)</script>', page, re.S).group(1))


def _title(html: str) -> str:
    """The view's title as plotly wrote it into the page (a JSON string)."""
    m = re.search(r'"text":"(deviation of the aligned source[^"]*)"', html)
    assert m, "no title"
    return json.loads(f'"{m.group(1)}"')


def test_view_colour_range_near_the_deviations(tmp_path):
    """A pair whose deviations spread over ±0.3 mm: the view's colours span ±300 µm, said in its title."""
    from scanreg.eval.metrics import EvalParams
    from scanreg.eval.view3d import write_view

    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 20, (5000, 2))  # mm
    target = Cloud(np.c_[xy, np.zeros(len(xy))], np.tile([0.0, 0.0, 1.0], (len(xy), 1)))
    dev = rng.uniform(-0.3, 0.3, len(xy))
    aligned = np.c_[xy, dev]
    on_surface = (target.points, np.abs(dev), target.normals)
    html = write_view(tmp_path / "view3d.html", target, Cloud(aligned), np.eye(4), aligned, on_surface, None,
                      EvalParams()).read_text()
    assert "colour range ±300 µm" in _title(html)
    assert re.search(r'"cmax":300(\.0)?[,}]', html) and re.search(r'"cmin":-300(\.0)?[,}]', html)
    fixed = write_view(tmp_path / "fixed.html", target, Cloud(aligned), np.eye(4), aligned, on_surface, None,
                       EvalParams(deviation_range=0.1)).read_text()
    assert "colour range ±100 µm" in _title(fixed)


def test_view_holds_the_points_and_deviations_it_was_given(tmp_path):
    """The page's figure (plotly.js JSON with base64 typed arrays) decodes to the aligned points and their signed
    deviations in display units, and to the target's points: the coordinates are not swapped, scaled or
    reordered on the way."""
    import base64

    from scanreg.eval.metrics import EvalParams
    from scanreg.eval.view3d import write_view

    rng = np.random.default_rng(1)
    xy = rng.uniform(0, 20, (3000, 2))
    target = Cloud(np.c_[xy, np.zeros(len(xy))], np.tile([0.0, 0.0, 1.0], (len(xy), 1)))
    dev = rng.uniform(-0.3, 0.3, len(xy))
    aligned = np.c_[xy[:, 1], xy[:, 0], dev]  # a different order of points than the target's
    on_surface = (np.c_[aligned[:, :2], np.zeros(len(xy))], np.abs(dev), target.normals)
    page = write_view(tmp_path / "view3d.html", target, Cloud(aligned), np.eye(4), aligned, on_surface, None,
                      EvalParams()).read_text()
    fig = _figure(page)

    def arr(a):
        return np.frombuffer(base64.b64decode(a["bdata"]), dtype="<f4")

    traces = {t["name"]: t for t in fig["data"]}
    shown = traces["source after alignment: signed deviation [µm]"]
    xyz = np.c_[arr(shown["x"]), arr(shown["y"]), arr(shown["z"])]
    np.testing.assert_allclose(xyz, aligned.astype(np.float32))
    np.testing.assert_allclose(arr(shown["marker"]["color"]), (dev * 1000).astype(np.float32), rtol=1e-6)
    tg = traces["target"]
    np.testing.assert_allclose(np.c_[arr(tg["x"]), arr(tg["y"]), arr(tg["z"])], target.points.astype(np.float32))


def test_the_deviations_are_shown_in_a_unit_that_follows_the_input():
    """Metre input (a bunny, an RGB-D cloud) shows its deviations in mm, millimetre input (a dental scan) in µm;
    ``units=auto`` tells them apart by the target's size; set units and display units are kept."""
    from scanreg.eval.metrics import EvalParams

    def shown(p, diagonal=None):
        q = p.shown(diagonal)
        return q.units, q.deviation_scale, q.deviation_unit

    assert shown(EvalParams(), 0.25) == ("m", 1000.0, "mm")  # the Stanford bunny
    assert shown(EvalParams(), 4.9) == ("m", 1000.0, "mm")  # a 3DMatch fragment
    assert shown(EvalParams(), 60.0) == ("mm", 1000.0, "um")  # a dental arch
    assert shown(EvalParams()) == ("mm", 1000.0, "um")  # no size known: as before units existed
    assert shown(EvalParams(units="cm"), 0.25) == ("cm", 10.0, "mm")
    assert shown(EvalParams(units="mm"), 0.25) == ("mm", 1000.0, "um")
    assert shown(EvalParams(deviation_scale=1.0, deviation_unit="m"), 0.25) == ("m", 1.0, "m")
    with pytest.raises(ValueError, match="deviation_scale and deviation_unit go together"):
        EvalParams(deviation_unit="mm").check()
    assert shown(EvalParams().shown(60.0), 0.25) == ("mm", 1000.0, "um")  # settled once, kept
    with pytest.raises(ValueError, match="units must be auto, m, cm, mm, um; got 'inch'"):
        EvalParams(units="inch").check()


def test_a_metre_scale_run_shows_millimetres(tmp_path):
    """The run on metre input (the bunny pair): its 3D view labels its colours in mm and says how it knew,
    greys the source beyond the fit's inlier distance (3 spacings) and colours the rest; the run logs its unit
    and its printed summary names it."""
    import base64

    from scanreg.api import register
    from scanreg.runner import summary_lines

    res = register(shared("stanford_bunny/bun045.ply"), shared("stanford_bunny/bun000.ply"), run_dir=tmp_path,
                   overrides=["repair=none"])
    page = (tmp_path / "view3d.html").read_text()
    assert "signed deviation [mm]" in page
    assert not any(u in page for u in ("[\\u00b5m]", "[µm]", " \\u00b5m", " µm"))
    # (its size along its principal axes, as every size check measures it, whatever the pose)
    assert re.search(r"input units: m, guessed from the target's size, 0\.2\d+ across", page)
    fig = _figure(page)
    traces = {t["name"].split(" (")[0]: t for t in fig["data"]}
    grey = traces["source after alignment, not compared"]
    assert f"farther than {3 * res.metrics['spacing'] * 1000:.3g} mm" in grey["name"]
    n_grey = len(base64.b64decode(grey["x"]["bdata"])) // 4
    n_on = len(base64.b64decode(traces["source after alignment: signed deviation [mm]"]["x"]["bdata"])) // 4
    assert abs(n_grey / (n_grey + n_on) - (1 - res.metrics["fitness"])) < 0.05  # the points off the fit
    assert res.metrics["input_unit_m"] == 1.0 and res.metrics["input_unit_guessed"] == 1.0
    assert "lengths in m, the input's unit (guessed from the target's size; set evaluate.units)" in \
        summary_lines(res)


def test_the_view_colours_the_overlap_and_says_what_it_shows(tmp_path):
    """Without a deviation map, the source points beyond ``max_distance`` (no overlap) are grey and do not set
    the colour range; a target without normals gives unsigned distances, coloured from 0; the page is named
    after the two files."""
    import base64

    from scanreg.eval.metrics import EvalParams
    from scanreg.eval.view3d import write_view

    rng = np.random.default_rng(2)
    xy = rng.uniform(0, 20, (2000, 2))
    target = Cloud(np.c_[xy, np.zeros(len(xy))])
    target.source = "/data/ref.ply"
    d = np.where(np.arange(len(xy)) < 1500, rng.uniform(0, 0.004, len(xy)), rng.uniform(0.5, 2.0, len(xy)))
    aligned = np.c_[xy, d]
    source = Cloud(aligned)
    source.source = "/data/scan 1.ply"
    page = write_view(tmp_path / "v.html", target, source, np.eye(4), aligned, (np.c_[xy, np.zeros(len(xy))], d, None),
                      None, EvalParams().shown(2.0), max_distance=0.01).read_text()
    assert "<title>scanreg: scan 1.ply onto ref.ply</title>" in page
    fig = _figure(page)
    traces = {t["name"]: t for t in fig["data"]}
    shown = traces["source after alignment: distance [mm]"]
    colours = np.frombuffer(base64.b64decode(shown["marker"]["color"]["bdata"]), dtype="<f4")
    assert len(colours) == 1500 and colours.max() < 4.0 + 1e-3  # the overlap only, in mm
    assert shown["marker"]["cmin"] == 0.0 and 3.0 <= shown["marker"]["cmax"] <= 4.0
    grey = traces["source after alignment, not compared (farther than 10 mm from the target)"]
    assert len(np.frombuffer(base64.b64decode(grey["x"]["bdata"]), dtype="<f4")) == 500
    assert fig["layout"]["title"]["text"].startswith("distance of the aligned source from the target (colour range 0 to 4 mm")


def test_a_pose_that_puts_little_of_the_source_on_the_target_is_warned_about(tmp_path, capsys):
    """A run whose fitness is below evaluate.fitness_warn says so in one warning line (bun180 onto bun000, which
    barely overlap, comes out at fitness 0.05-0.07 under a pose 48 degrees off: measured, too slow for here; a
    good run is made to warn by raising the threshold to 1); a run above it does not."""
    from scanreg.api import register
    from scanreg.eval.metrics import low_fitness_warning

    assert low_fitness_warning(0.0797, 0.1).startswith("only 8.0% of the source lies on the target after alignment")
    assert low_fitness_warning(0.1, 0.1) is None and low_fitness_warning(0.0, 0.0) is None
    bunny = pkg_file("pkg:pymeshfix/examples/StanfordBunny.ply")
    v = read_mesh(bunny).vertices
    far = v[::5] + 3 * np.ptp(v, axis=0)  # a fifth of the points far off the target: fitness about 0.83
    for threshold, warned in ((1.0, True), (0.1, False)):
        r = register(np.concatenate([v, far]), bunny, run_dir=tmp_path / str(threshold),
                     overrides=["repair=none", f"evaluate.fitness_warn={threshold}"])
        lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("warning: only")]
        assert lines == ([f"warning: {low_fitness_warning(r.metrics['fitness'], threshold)}"] if warned else [])


def test_a_deviation_map_on_a_target_without_normals_is_shown_as_distances(tmp_path):
    """With evaluate.deviation_map and a target cloud without normals the deviations carry no sign: the map
    says so, and the 3D view shows them as distances coloured from 0."""
    from scanreg.eval.deviation import evaluate_deviation
    from scanreg.eval.metrics import EvalParams
    from scanreg.eval.view3d import write_view
    from scanreg.geometry import ClosestPoints

    rng = np.random.default_rng(3)
    xy = rng.uniform(0, 20, (3000, 2))
    target = Cloud(np.c_[xy, np.zeros(len(xy))])
    src = Cloud(np.c_[xy[:1500] + 0.01, rng.uniform(-0.05, 0.05, 1500)])
    p = EvalParams(deviation_map=True).shown(28.0)
    _, _, view = evaluate_deviation(tmp_path, src, src, ClosestPoints(target), None, p)
    assert view["signed"] is False and (view["dev"] >= 0).all()
    page = write_view(tmp_path / "v.html", target, src, np.eye(4), src.points, None, view, p).read_text()
    assert "source after alignment: distance [\\u00b5m]" in page and '"cmin":0.0' in page


def test_files_with_a_users_preset_that_picks_its_own_scans(tmp_path):
    """A user's experiment in a ``--config-dir`` folder is looked at as the shipped ones are."""
    (tmp_path / "experiment").mkdir()
    (tmp_path / "experiment" / "mine.yaml").write_text("# @package _global_\ndefaults:\n  - override /data: stanford\n")
    with pytest.raises(ConfigError, match=r"with experiment=mine, whose data=stanford picks its own scans"):
        with_files(["a.ply", "b.ply", "--config-dir", str(tmp_path), "experiment=mine"])
    assert with_files(["a.ply", "b.ply", f"--config-dir={tmp_path}", "icp=gicp"])[-2:] == [
        "data.source='a.ply'", "data.target='b.ply'"]


def test_an_unknown_option_is_one_line():
    """A flag that is none of Hydra's (argparse printed its 8-line usage): one line; Hydra's own flags and their
    values, and a file whose name starts with '-', are no unknown option."""
    from scanreg.app.arguments import unknown_flag_error

    assert unknown_flag_error(["a.ply", "b.ply", "--foo"]).startswith("unknown option --foo: ")
    assert unknown_flag_error(["-x"]).startswith("unknown option -x: ")
    for ok in (["--cfg", "job", "-m"], ["--config-dir", "-odd-dir", "icp=gicp"], ["--config-dir=x", "--info", "config"],
               ["--help"], ["-cd", "x", "--multirun", "data.max_angle_deg=-5"]):
        assert unknown_flag_error(ok) is None, ok


def test_the_view_carries_plotly_packed_and_cached(tmp_path, monkeypatch):
    """The page's plotly.js is the package's file gzip-compressed (the page unpacks it: rendered offline in
    tests/test_uncertainty.py), compressed once into the user's cache folder; one that cannot be made is no
    error."""
    import base64
    import gzip

    from scanreg.eval import view3d

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    packed = view3d._plotly_js_packed()
    assert gzip.decompress(base64.b64decode(packed)) == view3d._plotly_js_path().read_bytes()
    assert len(packed) < 0.5 * view3d._plotly_js_path().stat().st_size
    cached = list((tmp_path / "cache" / "scanreg").iterdir())
    assert [p.suffix for p in cached] == [".b64"]  # (no temporary left)
    assert view3d._plotly_js_packed() == packed
    for cut in (len(packed) // 2 + 1, len(packed) // 8 * 4):  # damaged (cut short): made again, not served
        cached[0].write_text(packed[:cut])
        assert view3d._plotly_js_packed() == packed and cached[0].read_text() == packed
    (tmp_path / "file").write_text("")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "file"))  # a file where the folder would go
    assert view3d._plotly_js_packed() == packed


def test_each_data_provider_checks_its_files_before_reading_any(tmp_path):
    """``preflight`` (what a sweep checks for every job before the first starts) names a missing file or folder
    and a Stanford scan name that is not in its .conf, and reads no scan: a corrupt file that is there passes
    (it fails when the job reads it)."""
    from scanreg import build_stage
    from scanreg.errors import ConfigError, InputError

    (tmp_path / "corrupt.ply").write_bytes(b"not a mesh\n")
    (tmp_path / "bun.conf").write_text("bmesh corrupt.ply 0 0 0 0 0 0 1\nbmesh other.ply 0 0 0 0 0 0 1\n")
    (tmp_path / "other.ply").write_bytes(b"not a mesh either\n")
    ok = [("files", dict(source=str(tmp_path / "corrupt.ply"), target=str(tmp_path / "corrupt.ply"))),
          ("stanford", dict(folder=str(tmp_path), pair="corrupt:other")),
          ("synthetic", dict(mesh=str(tmp_path / "corrupt.ply"))),
          ("scanset", dict(scans=[str(tmp_path / "corrupt.ply"), str(tmp_path / "other.ply")]))]
    for name, params in ok:
        build_stage("data", name, **params).preflight()
    bad = [("files", dict(source=str(tmp_path / "corrupt.ply"), target="nope.ply"), InputError, "target nope.ply: no such file"),
           ("files", dict(source=str(tmp_path / "corrupt.ply"), target=None), ConfigError, "data.target is not set"),
           ("files", dict(source=str(tmp_path / "corrupt.ply"), target=str(tmp_path / "corrupt.ply"), gt="T.txt"),
            InputError, "ground truth data.gt T.txt: no such file"),
           ("stanford", dict(folder=str(tmp_path), pair="corrupt:othr"), ConfigError, "scan 'othr' is not in bun.conf"),
           ("stanford", dict(folder=str(tmp_path / "none")), InputError, "data.folder"),
           ("synthetic", dict(mesh="bunny.pyl"), InputError, "data.mesh bunny.pyl: no such file"),
           ("scanset", dict(scans=str(tmp_path / "*.stl")), InputError, "the pattern matches no file"),
           ("dental", dict(folder=str(tmp_path)), InputError, "data=dental: no folder"),
           ("pairs_3dmatch", dict(folder=str(tmp_path / "none")), InputError, "data.folder"),
           ("views", dict(mesh="nope.obj"), InputError, "data.mesh nope.obj: no such file")]
    for name, params, error, message in bad:
        with pytest.raises(error, match=re.escape(message)):
            build_stage("data", name, **params).preflight()
    (tmp_path / "other.ply").unlink()
    with pytest.raises(InputError, match="source .*other.ply: no such file"):
        build_stage("data", "stanford", folder=str(tmp_path), pair="corrupt:other").preflight()
