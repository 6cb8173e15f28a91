

@pytest.mark.parametrize("value", ["47.3,8.5", "north,8.5,400", "95,8.5,400"])
def test_synth_refuses_a_bad_gps_origin_writing_nothing(tmp_path, capsys, value):
    assert cli.main(["synth", "--out", str(tmp_path / "syn"), "--gps-origin", value, "--quiet"]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.count("--gps-origin") == 1, err
    assert not (tmp_path / "syn").exists()
