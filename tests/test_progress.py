"""Progress of long work: the stages a fit reports (a net of a tolerance search, a region
of an object), nested, and shown on the command line's bar."""
from __future__ import annotations

import threading

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import can, franke

from psonurbs import progress


def heard(work) -> list[tuple[str, int | None]]:
    """The stages reported while ``work()`` runs."""
    stages = []
    with progress.reporting(lambda text, iterations: stages.append((text, iterations))):
        work()
    return stages


def test_stages_nest_under_their_prefix_and_go_nowhere_without_a_receiver():
    def work():
        progress.stage("first", 1)
        with progress.within("region 2 of 3", None):
            progress.stage("net 4x4", 300)
            with progress.within("part 1"):
                progress.stage("net 3x3", 1)
        progress.stage("last")

    assert heard(work) == [("first", 1), ("region 2 of 3", None), ("region 2 of 3: net 4x4", 300),
                           ("region 2 of 3: part 1", None), ("region 2 of 3: part 1: net 3x3", 1), ("last", None)]
    work()  # no receiver: nothing to call, nothing raised

    def in_a_thread():
        thread = threading.Thread(target=lambda: progress.stage("from a thread of its own"))
        thread.start()
        thread.join()

    assert heard(in_a_thread) == []  # a thread starts without the receiver


def test_a_tolerance_search_reports_every_net_it_fits_and_the_one_it_delivers():
    from psonurbs.config import config_from_dict
    from psonurbs.fitting.pipeline import fit_points

    # the largest net 4 x 4: a short search (3 x 3, then 4 x 4), the tolerance out of its reach
    config = config_from_dict({"tolerance_rel": 1e-3, "net_size": [4, 4], "swarm": {"particles": 1, "iterations": 1}})
    results = []
    stages = heard(lambda: results.append(fit_points(franke(400, noise=0.0), config)))
    searched = results[0].info["tolerance"]["searched"]
    nu, nv = results[0].info["tolerance"]["net_size"]
    assert stages == [(f"searched net {k}: {s['net_size'][0]}x{s['net_size'][1]}, uniform knots", 1)
                      for k, s in enumerate(searched, 1)] + [(f"the chosen net {nu}x{nv}, uniform knots, on every "
                                                              "point", 1)]
    assert [text for text, _ in stages][:2] == ["searched net 1: 3x3, uniform knots", "searched net 2: 4x4, uniform knots"]


def test_an_objects_regions_are_reported_in_turn_with_their_points():
    from psonurbs.config import config_from_dict
    from psonurbs.objects.whole import fit_object

    class Enough(Exception):
        pass

    sizes = []

    def fit(points, config, on_iteration=None):
        sizes.append(len(points))
        progress.stage("inside", 1)
        if len(sizes) == 2:
            raise Enough

    config = config_from_dict({"patches": "auto", "swarm": {"particles": 1, "iterations": 1}})
    stages = []
    with pytest.raises(Enough), progress.reporting(lambda text, iterations: stages.append(text)):
        fit_object(can(3000), config, fit=fit)
    first, second = (f"region {k} of 3 ({n} points)" for k, n in zip((1, 2), sizes))
    assert stages == ["regions grown on the normals, parted at creases", first, f"{first}: inside", second,
                      f"{second}: inside"]


def test_the_command_lines_bar_names_the_net_a_search_is_fitting(tmp_path, monkeypatch):
    import cli.main

    cloud = tmp_path / "franke.xyz"
    np.savetxt(cloud, franke(400, noise=0.0))
    config = tmp_path / "short.yaml"
    config.write_text("net_size: [4, 4]\ntolerance_rel: 1.0e-3\n")  # a short search: 3 x 3, then 4 x 4
    monkeypatch.setattr(cli.main, "_progress_enabled", lambda quiet: not quiet)  # as on a terminal
    result = CliRunner().invoke(cli.main.cli, ["fit", str(cloud), "-c", str(config), "-o", str(tmp_path / "out"),
                                               "--particles", "1", "--iterations", "1"])
    assert result.exit_code == 0, result.output
    assert "franke.xyz: searched net 1: 3x3, uniform knots" in result.stderr
    assert "franke.xyz: searched net 2: 4x4, uniform knots" in result.stderr
    assert "franke.xyz: the chosen net 4x4, uniform knots, on every point" in result.stderr
