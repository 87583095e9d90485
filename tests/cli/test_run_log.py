import logging
import sys

from shapecorr.cli.run_log import PlainLines, run_log


def test_carriage_returns_become_lines():
    plain = PlainLines()
    assert plain("\rbar 1/3") + plain("\rbar 2/3") + plain("\rbar 3/3\n") == "bar 1/3\nbar 2/3\nbar 3/3\n"
    assert PlainLines()("a\x1b[A\r\nb") == "a\nb"


def test_run_log_copies_prints_warnings_and_records(tmp_path, capsys):
    with run_log(tmp_path / "out", "evaluate") as path:
        print("summary line")
        print("\rprogress 1\rprogress 2", file=sys.stderr)
        logging.getLogger("shapecorr.test").warning("a record")
    text = path.read_text()
    assert path == tmp_path / "out" / "evaluate.log"
    assert "summary line\n" in text and "progress 1\nprogress 2" in text and "a record" in text
    assert "summary line" in capsys.readouterr().out  # still printed
    with run_log(tmp_path / "out", "evaluate"):
        print("resumed")
    assert path.read_text().startswith(text) and path.read_text().endswith("resumed\n")
