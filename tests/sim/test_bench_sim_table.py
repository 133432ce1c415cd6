"""``iristac bench sim`` prints every target with met / NOT met and the rows behind it (format only, no timing)."""

from pipeline.bench.sim import TARGETS, _verdict, format_table


def test_targets_table_prints_each_target_met_or_not():
    tg = {"cli_rays": 10_000_000, "rays": 10_000_000, "compile_seconds": 12.0, "fresh_wall_seconds": 2.1,
          "fresh_load_seconds": 0.9, "trace_seconds": 0.15, "trace_Mrays_per_s": 66.0, "all24_over_one": 1.4,
          "peak_memory_mb": 300.0, "one_led_seconds": 0.1, "all24_seconds": 0.14, "kernel_only_seconds": 0.09,
          "in_process_Mrays_per_s": {"one": 100.0, "all24": 71.4, "kernel": 111.1},
          "first_run": {"wall_seconds": 14.0, "cpu_seconds": 13.0, "compile_seconds": 12.0, "seconds": 0.15},
          "fresh_runs": [{"wall_seconds": 2.1, "cpu_seconds": 1.9, "compile_seconds": 0.9, "seconds": 0.15,
                          "rays_per_second": 6.6e7}],
          "peak_memory": {"rays": 100_000_000, "peak_rss_mb": 300.0, "seconds": 1.6},
          "eager": {"rays": 1_000_000, "rows": [{"threads": 1, "torch_Mrays_per_s": 3.7, "kernel_Mrays_per_s": 33.0,
                                                 "speedup": 8.9}]},
          "agreement": {"E_rel_L1": 1e-4, "V_rel_L1": 1.5e-4, "energy_max_abs_diff": 1e-8, "counters_equal": True},
          "plano_sphere_Mrays_per_s": 40.0}
    tg["targets"] = [_verdict(tg, *t) for t in TARGETS]
    res = {"device": "cpu", "threads": 2, "repeats": 3, "quick": False, "load_average": [1.0, 1.0, 1.0],
           "targets": tg}
    lines = format_table(res).splitlines()
    verdicts = {t["target"]: t["met"] for t in tg["targets"]}
    assert verdicts == {"fresh_wall_seconds": True, "compile_seconds": True, "trace_Mrays_per_s": True,
                        "all24_over_one": False, "peak_memory_mb": True}
    assert sum(ln.split()[0] == "met" for ln in lines if ln.strip()) == 4
    assert any(ln.split()[:2] == ["NOT", "met"] and "24 LEDs" in ln for ln in lines)
    assert any("first-ever run" in ln and "12.00 s compiling" in ln for ln in lines)
    assert any("peak memory at 100,000,000 rays: 300 MB" in ln for ln in lines)
    assert any("counters equal" in ln for ln in lines)
