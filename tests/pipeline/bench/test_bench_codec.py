"""``iristac bench codec`` runs end to end (--quick, three of its candidates) and prints its
table; the figures themselves are measured by the benchmark, never asserted here."""

import json

from helpers import run_cli


def test_bench_codec_quick_prints_its_table_and_every_read_is_exact():
    r = run_cli("bench", "codec", "--quick", "--codecs", "lzf,raw,zstd:-1", timeout=300)
    assert r.returncode == 0, r.stderr
    head = r.stdout.splitlines()
    assert any(line.split()[:2] == ["frames", "codec"] for line in head)
    for frames in ("gelsight 160x120", "digit 480x640", "virtual 320x240"):
        if f"{frames.split()[0]}: left out" in r.stdout:  # shared/data is not beside this checkout
            continue
        for codec in ("lzf ", "raw ", "zstd:-1*"):
            assert any(line.startswith(frames) and f" {codec}" in line and line.rstrip().endswith("yes")
                       for line in head), (frames, codec, r.stdout)


def test_bench_codec_json_rows_and_an_unknown_codec():
    r = run_cli("bench", "codec", "--quick", "--codecs", "zstd:-1", "--json", timeout=300)
    assert r.returncode == 0, r.stderr
    res = json.loads(r.stdout)
    assert res["chosen"] == "zstd:-1" and all(x["exact"] for x in res["results"])
    assert res["rows"] and all({"knob", "setting", "error", "seconds"} <= set(row) and row["default"]
                               for row in res["rows"])
    bad = run_cli("bench", "codec", "--quick", "--codecs", "gzip", timeout=120)
    assert bad.returncode != 0 and "unknown codec gzip" in bad.stderr
