"""The training loop's progress bar where stderr is a file or a pipe."""

from c3dpo_jax import progress


def test_the_progress_bar_writes_whole_lines_when_stderr_is_not_a_terminal(monkeypatch):
    import io

    stream = io.StringIO()  # a log file or a pipe: isatty() is False
    monkeypatch.setattr("sys.stderr", stream)
    bar = progress.progress_bar(total=100, desc="train", unit="step")
    for _ in range(4):
        bar.update(25)
    bar.close()
    lines = stream.getvalue().splitlines()
    assert "\r" not in stream.getvalue() and stream.getvalue().endswith("\n")
    assert lines[0].startswith("train:   0%") and "100/100" in lines[-1]
    assert len(lines) <= 3  # the start, the end, and a line per 30 s between
