"""The HTML report writer produces a page whose images exist and whose JSON round-trips."""

import json
import re

import numpy as np

from pipeline.results.report import Report, to_uint8_image


def test_report_page_references_existing_images_and_writes_json(tmp_path):
    r = Report("Demo <test>", "intro")
    s = r.section("Errors per mode")
    s.table(["mode", "mean (deg)"], [["point", 1.23456], ["multicolour", np.float32(2.5)]])
    s.image("normals: point", np.random.default_rng(0).random((8, 10, 3)))
    s.image("depth", np.linspace(0, 1, 80).reshape(8, 10))
    out = r.write(tmp_path / "rep", data={"modes": {"point": np.float64(1.5)}})
    page = (out / "report.html").read_text()
    assert "Demo &lt;test&gt;" in page and "<td>1.235</td>" in page
    srcs = re.findall(r'src="([^"]+)"', page)
    assert len(srcs) == 2 and all((out / s).is_file() for s in srcs)
    assert json.loads((out / "report.json").read_text()) == {"modes": {"point": 1.5}}


def test_to_uint8_image_handles_float_uint16_and_nonfinite():
    assert to_uint8_image(np.array([[0.0, 1.0, 2.0, np.nan]])).tolist() == [[0, 255, 255, 0]]
    assert to_uint8_image(np.array([[65535]], np.uint16)).tolist() == [[255]]
