"""The release's dataset files: names -> URLs, md5 sums, a local cache, and downloads.

Files live at ``https://dl.fbaipublicfiles.com/c3dpo_nrsfm/{name}_{split}.json``. They
are cached in ``data_dir`` (argument) > ``$C3DPO_DATA_DIR`` > ``~/.cache/c3dpo_jax``.
A download goes to a temporary file in that directory, is checked against the
release's md5 (none was published for cub_birds*, up3d_79kp_val) and is then renamed
atomically, so an interrupted download never leaves a truncated file behind.
"""

import hashlib
import os
import tempfile
import urllib.error
import urllib.request

from absl import logging
from tqdm import tqdm

BASE_URL = "https://dl.fbaipublicfiles.com/c3dpo_nrsfm"
ENV_VAR = "C3DPO_DATA_DIR"

MD5 = {
    "cub_birds_hrnet_train.json": None,
    "cub_birds_hrnet_val.json": None,
    "cub_birds_train.json": None,
    "cub_birds_val.json": None,
    "h36m_hourglass_train.json": "d2ffcaf4ce9e49712a65e2b1932814a3",
    "h36m_hourglass_val.json": "9996a703cb3b24da3b5563baa09da2bd",
    "h36m_train.json": "454e2aee4cad761499265f858fe2e0ff",
    "h36m_val.json": "d2347fc651e7f704ce3a4da880852fff",
    "pascal3d_hrnet_train.json": "c145b879e7462f8942a258f7c6dcbee4",
    "pascal3d_hrnet_val.json": "5cb55986b1c19253f0b8213e47688443",
    "pascal3d_train.json": "a78048a101ef56bc371b01f66c19178b",
    "pascal3d_val.json": "0128817c43eaa1eff268d5295700c8ad",
    "up3d_79kp_test.json": "7d8bf3405ec085394e9257440e8bcb18",
    "up3d_79kp_train.json": "fde2aee038ecd0f145181559eff59c9f",
    "up3d_79kp_val.json": None,
}

# Evaluation protocol of each release dataset (see evaluation.py); "none": no 3D GT.
PROTOCOLS = {
    "h36m": "h36m", "h36m_hourglass": "h36m",
    "pascal3d": "pascal3d", "pascal3d_hrnet": "pascal3d",
    "up3d_79kp": "up3d",
    "cub_birds": "none", "cub_birds_hrnet": "none",
}
# The split the release evaluates on.
EVAL_SPLIT = {name: ("test" if name == "up3d_79kp" else "val") for name in PROTOCOLS}


class DownloadError(OSError):
    """A file could not be fetched; the message says how to get it by hand."""


def data_dir(override: str | None = None) -> str:
    """The cache directory: ``override`` > ``$C3DPO_DATA_DIR`` > ``~/.cache/c3dpo_jax``."""
    path = override or os.environ.get(ENV_VAR) or os.path.join("~", ".cache", "c3dpo_jax")
    return os.path.abspath(os.path.expanduser(path))


def file_url(filename: str, base_url: str = BASE_URL) -> str:
    return f"{base_url.rstrip('/')}/{filename}"


def md5sum(path: str) -> str:
    h = hashlib.md5()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _by_hand(url: str, dest: str) -> str:
    return (f"download it by hand (e.g. `curl -L -o {dest} {url}` or a browser) and put it at "
            f"{dest}, or point ${ENV_VAR} (or data_dir=) at a directory that holds it")


def _stream(response, out, total: int | None, progress: bool, desc: str) -> str:
    h = hashlib.md5()
    with tqdm(total=total, unit="B", unit_scale=True, desc=desc, disable=not progress) as bar:
        for block in iter(lambda: response.read(1 << 20), b""):
            out.write(block)
            h.update(block)
            bar.update(len(block))
    return h.hexdigest()


def fetch(filename: str, *, directory: str | None = None, base_url: str = BASE_URL,
          md5: str | None = "release", progress: bool = True, timeout: float | int = 60.0) -> str:
    """Returns the local path of ``filename``, downloading it first if it is absent.

    Args:
      filename: e.g. ``"h36m_train.json"``.
      directory: cache directory (see ``data_dir``).
      base_url: where the files are served.
      md5: expected md5; ``"release"`` looks it up in ``MD5``; ``None`` skips the check.
      progress: show a tqdm progress bar.
      timeout: seconds to wait for the server.
    """
    directory = data_dir(directory)
    dest = os.path.join(directory, filename)
    if os.path.exists(dest):
        return dest
    if md5 == "release":
        md5 = MD5.get(filename)
    url = file_url(filename, base_url)
    os.makedirs(directory, exist_ok=True)
    logging.info("downloading %s -> %s", url, dest)
    fd, tmp = tempfile.mkstemp(dir=directory, prefix=f".{filename}.", suffix=".part")
    try:
        with os.fdopen(fd, "wb") as out:
            try:
                with urllib.request.urlopen(url, timeout=timeout) as response:
                    size = response.headers.get("Content-Length")
                    got = _stream(response, out, int(size) if size else None, progress, filename)
            except (urllib.error.URLError, TimeoutError, ConnectionError) as err:
                raise DownloadError(
                    f"could not download {url} ({getattr(err, 'reason', err)}); are you "
                    f"offline? {_by_hand(url, dest)}") from None
        if md5 is not None and got != md5:
            raise DownloadError(f"md5 mismatch for {url}: expected {md5}, got {got} (a "
                                f"truncated or changed file); retry, or {_by_hand(url, dest)}")
        os.replace(tmp, dest)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return dest


def protocol(name: str) -> str:
    """The evaluation protocol of a release dataset (``"none"``: no 3D ground truth)."""
    if name not in PROTOCOLS:
        raise ValueError(f"unknown release dataset {name!r}; known: {sorted(PROTOCOLS)}")
    return PROTOCOLS[name]


def dataset_files(name: str, *, directory: str | None = None, base_url: str = BASE_URL,
                  download: bool = True, progress: bool = True) -> tuple[str, str]:
    """``(train_path, test_path)`` of a release dataset, downloaded when absent.

    The test file is the split the release evaluates on (``up3d_79kp``: ``_test``,
    others: ``_val``); ``protocol(name)`` gives the evaluation protocol.
    """
    protocol(name)
    names = (f"{name}_train.json", f"{name}_{EVAL_SPLIT[name]}.json")
    if not download:
        return tuple(os.path.join(data_dir(directory), n) for n in names)
    return tuple(fetch(n, directory=directory, base_url=base_url, progress=progress)
                 for n in names)
