"""``iristac bench sim`` prints the targets section with its thread counts (format only, no timing)."""

from pipeline.bench.sim import format_table


def test_targets_table_names_path_threads_and_ratios():
    row = {"compiled": True, "threads": 2, "one_led_seconds": 0.04, "one_led_Mrays_per_s": 25.0,
           "one_led_cpu_seconds": 0.07, "kernel_only_Mrays_per_s": 27.0, "all24_seconds": 0.06,
           "all24_cpu_seconds": 0.09, "all24_over_one": 1.5, "all24_over_one_cpu": 1.29, "energy_residual": 2.6e-9,
           "retraced": 2160}
    res = {"device": "cpu", "threads": 2, "repeats": 3, "quick": False, "load_average": [1.0, 1.0, 1.0],
           "targets": {"rays": 1_000_000, "rows": [dict(row, compiled=False, threads=1), row],
                       "compiled_vs_eager": {"E_rel_L1": 7e-5, "V_rel_L1": 1e-4}, "plano_sphere_Mrays_per_s": 7.0,
                       "peak_memory": [{"compiled": True, "rays": 9_998_244, "peak_rss_mb": 640.0,
                                        "rss_before_mb": 640.0, "seconds": 0.3}]}}
    text = format_table(res)
    lines = text.splitlines()
    assert any(ln.split()[:2] == ["eager", "1"] for ln in lines)
    assert any(ln.split()[:2] == ["compiled", "2"] and "25.00" in ln and "1.29" in ln for ln in lines)
    assert "threads" in text and "peak memory (compiled) at 9,998,244 rays: 640 MB" in text
