"""The training loop's progress bar: tqdm's widget bar in a notebook that has ipywidgets,
its text bar in a terminal, and one line per redraw where stderr is a file or a pipe.
"""

import importlib.util
import sys


class _BarLines:
    """The progress bar's stream where stderr is a file or a pipe (a log, ``| tee``, a batch
    job): each redraw becomes one line, where a terminal's carriage returns would pile every
    update into one line thousands of characters long."""

    def __init__(self, stream):
        self.stream, self.last = stream, ""

    def write(self, text: str) -> None:
        line = text.replace("\r", "").strip("\n")
        if line.strip() and line != self.last:
            self.stream.write(line + "\n")
            self.last = line

    def flush(self) -> None:
        self.stream.flush()


def progress_bar(**kwargs):
    """tqdm's widget bar in a notebook that has ipywidgets, else its text bar (importing
    tqdm.auto would warn "IProgress not found" in every notebook without ipywidgets); where
    stderr is not a terminal (nor a notebook), a line every 30 s (``_BarLines``)."""
    notebook = "ipykernel" in sys.modules
    if notebook and importlib.util.find_spec("ipywidgets") is not None:
        from tqdm.auto import tqdm
    else:
        from tqdm import tqdm
    if not notebook and not sys.stderr.isatty():
        kwargs.update(file=_BarLines(sys.stderr), mininterval=30.0, ncols=100,
                      dynamic_ncols=False)
    return tqdm(**kwargs)
