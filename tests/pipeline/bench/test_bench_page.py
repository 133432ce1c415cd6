"""The benchmark page (iristac bench report) over real HTTP and in headless Chromium.

Built from the committed docs/benchmarks.json (a real run), through the CLI. Chromium is
driven over the DevTools protocol (tests/cdp_chromium.py says why): every chart draws, no
console error, exception or failed request, no two labels overlap, the stage selector
filters, a hover shows the exact figures and the machine, a screenshot is not blank.
"""

import json
import re
import urllib.request

import pytest

from cdp_chromium import CHART_CHECK_JS, Chromium, blank_fraction, find_chromium, serve
from helpers import REPO, run_cli

RESULTS = REPO / "docs" / "benchmarks.json"
needs_chromium = pytest.mark.skipif(find_chromium() is None,
                                    reason="no chromium on PATH (Debian: apt-get install -y chromium; .ci/run "
                                           "installs it where apt is available)")


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    d = tmp_path_factory.mktemp("site")
    r = run_cli("bench", "report", RESULTS, "--out", d / "page.html", "--figure", d / "summary.png", "--json")
    assert r.returncode == 0, r.stderr
    with serve(d) as url:
        yield d, url, json.loads(r.stdout)


def test_the_page_is_served_and_needs_nothing_from_the_network(site):
    d, url, result = site
    with urllib.request.urlopen(f"{url}/page.html", timeout=10) as resp:
        assert resp.status == 200 and resp.headers["Content-Type"].startswith("text/html")
        page = resp.read().decode()
    srcs = re.findall(r'<(?:script|link)[^>]+(?:src|href)="([^"]+)"', page)
    assert srcs and not [s for s in srcs if "//" in s], srcs  # no CDN, nothing absolute
    for s in (s for s in srcs if s.endswith(".js")):
        with urllib.request.urlopen(f"{url}/{s}", timeout=10) as resp:
            assert resp.status == 200 and b"plotly" in resp.read(2000).lower()
    assert page.count('class="chart"') == len(result["charts"]) >= 10
    assert (d / "summary.png").stat().st_size > 20_000


@needs_chromium
def test_every_chart_renders_without_errors_labels_apart(site, tmp_path):
    _, url, result = site
    with Chromium() as browser:
        page = browser.open(f"{url}/page.html", ready="document.body.dataset.rendered")
        assert int(page.evaluate("document.body.dataset.rendered")) == len(result["charts"])
        charts = page.evaluate(CHART_CHECK_JS)
        assert len(charts) == len(result["charts"])
        by_id = {c["id"]: c for c in charts}
        for c in result["charts"]:
            drawn = by_id[f"chart-{c['key']}"]
            assert drawn["svg"] and drawn["points"] >= c["points"], drawn
            assert drawn["labels"] >= c["points"] and drawn["overlaps"] == 0, drawn
        # hover: the exact figures and the machine
        text = page.evaluate("""(() => { const gd = document.getElementById('chart-live-320x240');
            const trace = gd.data.findIndex(t => t.customdata);
            Plotly.Fx.hover(gd, [{curveNumber: trace, pointNumber: 0}]);
            return gd.querySelector('.hoverlayer').textContent; })()""")
        assert "machine" in text and "error" in text and "seconds" in text, text
        # the stage selector
        shown = page.evaluate("""(() => { const s = document.getElementById('stage'); s.value = 'live';
            s.dispatchEvent(new Event('change'));
            return [...document.querySelectorAll('figure.chart')].filter(f => !f.classList.contains('hidden'))
                .map(f => f.dataset.stages); })()""")
        assert shown and all("live" in s.split() for s in shown)
        assert len(shown) < len(result["charts"])
        png = page.screenshot()
        assert page.errors == []
    white, std = blank_fraction(png)
    assert white < 0.97 and std > 20, (white, std)
