"""Charts of what accuracy costs in time: the front, the labels, the views, the sentences, the figures."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.base.errors import UserError
from pipeline.charts.decisions import build_charts, overview, summary_charts
from pipeline.charts.labels import boxes_overlap, chart_placement, place_labels
from pipeline.charts.model import Chart, Point, front_indices
from pipeline.charts.rows import load_results
from pipeline.charts.static import summary_figure


def _row(knob, setting, error, seconds, bench="live", **kw):
    return dict(kw, knob=knob, setting=setting, error=error, error_unit="deg", seconds=seconds, bench=bench,
                machine="test machine")


@given(st.lists(st.tuples(st.floats(1e-4, 10.0), st.floats(1e-4, 10.0)), min_size=1, max_size=25))
@settings(max_examples=60, deadline=None)
def test_the_front_holds_exactly_the_undominated_points(xy):
    pts = [Point(x, y, str(i)) for i, (x, y) in enumerate(xy)]
    front = set(front_indices(pts))

    def dominates(q, p):
        return q.x <= p.x and q.y <= p.y and (q.x < p.x or q.y < p.y)

    for i, p in enumerate(pts):
        assert (i in front) == (not any(dominates(q, p) for q in pts))


def test_labels_of_crowded_points_stay_apart_inside_and_off_the_markers():
    rng = np.random.default_rng(3)
    for trial in range(20):
        n = int(rng.integers(2, 14))
        pts = rng.uniform([40, 30], [700, 300], size=(n, 2))
        pts[: n // 2] = pts[0] + rng.normal(0, 8, size=(n // 2, 2))  # a tight cluster
        texts = [f"setting {k} x{int(rng.integers(1, 999))}" for k in range(n)]
        pl = place_labels(pts, texts, 760, 340)
        assert pl.overlaps == 0, trial
        for i, a in enumerate(pl.boxes):
            assert a[0] >= 0 and a[1] >= 0 and a[2] <= 760 and a[3] <= 340
            assert not any(boxes_overlap(a, b) for b in pl.boxes[i + 1:])
            assert not any(boxes_overlap(a, (x - 5, y - 5, x + 5, y + 5)) for x, y in pts)


def _live_rows():
    rows = []
    for solver, err, t in (("nearfield", 0.18, 0.004), ("lut", 0.07, 0.0036), ("mlp", 0.69, 0.0099)):
        for th, f in ((1, 1.0), (2, 0.7)):
            rows.append(_row(f"live {solver} @ 320x240", f"fast, {th} thread(s)", err, t * f, threads=th,
                             path="fast", default=(solver, th) == ("lut", 1)))
        rows.append(_row(f"live {solver} @ 320x240", "eager, 1 thread(s)", err, t * 8, threads=1, path="eager"))
    return rows


def test_live_rows_answer_the_live_question_and_the_fast_path_and_threads_questions():
    charts = {c.key: c for c in build_charts(_live_rows())}
    live = charts["live-320x240"]
    assert {p.series for p in live.points} == {"nearfield", "lut", "mlp"} and len(live.points) == 6
    assert live.sentence.startswith("Within a 60 fps camera's frame time (16.7 ms), the most accurate is lut "
                                    "2 threads")
    assert sum(p.default for p in live.points) == 1
    assert "8x the speed over 3 cases" in charts["path"].sentence
    assert "the speed over 3 cases" in charts["threads"].sentence


def test_new_rows_with_device_or_threads_fields_appear_without_code_changes():
    rows = _live_rows() + [_row("live nearfield @ 320x240", "batched", 0.18, 0.0005, device="cuda", path="fast",
                                threads=1)]
    charts = {c.key: c for c in build_charts(rows)}
    labels = {p.label for p in charts["threads"].points}
    assert "cuda 1 thread" in labels
    # a knob no view knows gets its own chart; a single setting goes into a table
    rows += [_row("new knob", "a", 1.0, 0.1, bench="sim"), _row("new knob", "b", 0.5, 0.2, bench="sim"),
             _row("lonely knob", "only", 1.0, 0.1, bench="sim")]
    ov = overview(rows)
    assert any(c.title == "new knob" for c in ov.charts)
    assert [t["why"] for t in ov.tables if t["knob"] == "lonely knob"] == ["a single setting"]


def test_zero_error_or_time_sits_on_the_axis_floor_and_says_so():
    c = Chart("k", "t", "seconds", "error (deg)", [Point(0.0, 1.0, "free"), Point(0.1, 0.0, "exact")])
    pl = chart_placement(c, 600, 300, 11)
    assert pl.overlaps == 0
    from pipeline.charts.model import point_label

    assert [point_label(p) for p in c.points] == ["free (time = 0)", "exact (error = 0)"]


def test_mode_rows_contrast_point_and_trichromatic():
    from pipeline.workflows.compare_modes import comparison_rows

    runs = [{"mode": m, "solver": s, "patterns": p, "capture_seconds": cap, "capture_seconds_source": "measured",
             "reconstruct_seconds": rt, "normal_mean_error_deg": e, "depth_rmse_mm": 0.05, "valid_fraction": 1.0}
            for m, s, p, cap, rt, e in (("point", "robust", 24, 5.5, 0.6, 0.13), ("point", "nearfield", 24, 5.5, 0.4,
                                                                                   0.62),
                                        ("trichromatic", "nearfield", 1, 0.21, 0.08, 0.89),
                                        ("trichromatic", "lut", 1, 0.21, 0.07, 0.97))]
    charts = {c.key: c for c in build_charts(comparison_rows(runs, default=("trichromatic", "lut")))}
    cap = charts["modes-capture"]
    assert len(cap.points) == 3  # the best solver per mode, and the default
    assert cap.sentence.startswith("Point over trichromatic, the best solver of each: 0.13 deg (robust) against "
                                   "0.89 deg (nearfield), 6.85x less error, for 26x the capture time")
    assert len(charts["modes-recon"].points) == 4


def test_summary_figure_is_900_px_wide_with_at_most_six_panels(tmp_path):
    ov = overview(_live_rows())
    charts = summary_charts(ov.charts) + [ov.charts[0]] * 5
    out = summary_figure(charts[:6], tmp_path / "s.png")
    assert out["size"][0] == 900 and out["panels"] == 6
    import cv2

    img = cv2.imread(str(tmp_path / "s.png"))
    assert img.shape[1] == 900 and img.std() > 20


def test_a_bad_results_file_is_refused_naming_it(tmp_path):
    p = tmp_path / "r.json"
    p.write_text("[1, 2]")
    with pytest.raises(UserError, match="r.json: expected an object with 'sections'"):
        load_results(p)
    p.write_text('{"sections": [{"bench": "sim", "rows": [{"setting": "x"}]}]}')
    with pytest.raises(UserError, match=r"sections\[0\] \(sim\) rows\[0\] has no 'knob' field"):
        load_results(p)


def test_the_default_is_not_called_slower_within_the_timing_noise():
    """A point faster than the default by less than the repeats' noise (or 10 %) is "as fast";
    beyond it, "faster"; equal errors (within 1 %) are "as accurate", never "more accurate"."""
    from pipeline.charts.sentences import default_status

    def status(q_x, q_y, noise):
        d = Point(0.0100, 1.0, "default", default=True, x_noise=noise)
        return default_status(Chart("k", "t", "seconds", "error (deg)", [d, Point(q_x, q_y, "other", x_noise=noise)]))

    assert "as fast as other" in status(0.0095, 0.5, 0.01) and "more accurate" in status(0.0095, 0.5, 0.01)
    assert "is faster and more accurate" in status(0.0080, 0.5, 0.01)
    assert "as fast as other" in status(0.0080, 0.5, 0.15)  # 25 % faster, but the repeats wander 15 %
    assert "faster and as accurate" in status(0.0050, 0.999, 0.01)
    assert "ties with other" in status(0.0095, 0.999, 0.01)
