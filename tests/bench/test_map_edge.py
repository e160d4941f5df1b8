"""bench.map_edge: matchers on the map so far against a complete map, from the true poses."""

from __future__ import annotations

from bench.map_edge import main, run


def test_gn_is_pulled_where_the_map_ends_and_gn_plicp_is_not() -> None:
    """4 s of the rooms world: gn's heading spreads 0.19 deg on the map so far against 0.025 on
    the complete map; gn+plicp stays near its complete-map figure."""
    report = run("rooms", 4.0, ["gn", "gn+plicp"])
    assert report["matches"] == (report["scans"] - 1) // 2
    gn, fine = report["methods"]["gn"], report["methods"]["gn+plicp"]
    assert gn["so_far"]["theta_std_deg"] > 3 * gn["complete"]["theta_std_deg"]
    assert gn["so_far"]["x_std_mm"] > 3 * gn["complete"]["x_std_mm"]
    assert fine["so_far"]["theta_std_deg"] < 0.3 * gn["so_far"]["theta_std_deg"]
    assert fine["so_far"]["x_std_mm"] < 0.3 * gn["so_far"]["x_std_mm"]


def test_the_command_line_prints_the_report(capsys) -> None:
    main(["--duration", "1.0", "--methods", "gn", "--json"])
    out = capsys.readouterr().out
    assert '"world": "rooms"' in out and '"gn"' in out and '"so_far"' in out
