"""Release downloader against a loopback HTTP server; never contacts an external host."""

import contextlib
import functools
import hashlib
import http.server
import importlib
import os
import socket
import threading

import pytest

from c3dpo_jax.data import download

PAYLOAD = b'[{"kp_loc": [[0, 1, 2], [0, 1, 2]], "kp_vis": [1, 1, 1]}]' * 50


@contextlib.contextmanager
def _server(directory):
    handler = functools.partial(_QuietHandler, directory=str(directory))
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.05},
                              daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()
        httpd.server_close()
        thread.join(timeout=5)


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


@pytest.fixture
def served(tmp_path):
    root = tmp_path / "server"
    root.mkdir()
    (root / "toy_train.json").write_bytes(PAYLOAD)
    with _server(root) as url:
        yield url


def test_fetch_downloads_verifies_and_renames_atomically(served, tmp_path):
    md5 = hashlib.md5(PAYLOAD).hexdigest()
    cache = tmp_path / "cache"
    path = download.fetch("toy_train.json", directory=str(cache), base_url=served, md5=md5,
                          progress=False, timeout=5)
    assert path == str(cache / "toy_train.json")
    assert _read(path) == PAYLOAD
    assert os.listdir(cache) == ["toy_train.json"]  # no temporary file left behind
    # Present files are not downloaded again (the server is not needed).
    assert download.fetch("toy_train.json", directory=str(cache), base_url="http://127.0.0.1:9",
                          progress=False) == path


def test_md5_mismatch_raises_and_leaves_nothing(served, tmp_path):
    cache = tmp_path / "cache"
    with pytest.raises(download.DownloadError, match="md5 mismatch .* expected 0+, got"):
        download.fetch("toy_train.json", directory=str(cache), base_url=served, md5="0" * 32,
                       progress=False, timeout=5)
    assert os.listdir(cache) == []


def test_offline_error_explains_the_manual_download(tmp_path):
    with socket.socket() as s:  # a port with nothing listening on it
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(download.DownloadError) as err:
        download.fetch("h36m_train.json", directory=str(tmp_path), progress=False, timeout=5,
                       base_url=f"http://127.0.0.1:{port}")
    msg = str(err.value)
    assert "are you offline?" in msg and "download it by hand" in msg
    assert str(tmp_path / "h36m_train.json") in msg and "C3DPO_DATA_DIR" in msg
    assert os.listdir(tmp_path) == []


def test_data_dir_precedence(monkeypatch, tmp_path):
    monkeypatch.delenv(download.ENV_VAR, raising=False)
    assert download.data_dir() == os.path.expanduser("~/.cache/c3dpo_jax")
    monkeypatch.setenv(download.ENV_VAR, str(tmp_path / "env"))
    assert download.data_dir() == str(tmp_path / "env")
    assert download.data_dir(str(tmp_path / "arg")) == str(tmp_path / "arg")


def test_dataset_files_and_protocols(tmp_path):
    train, test = download.dataset_files("up3d_79kp", directory=str(tmp_path), download=False)
    assert train.endswith("up3d_79kp_train.json") and test.endswith("up3d_79kp_test.json")
    assert download.dataset_files("h36m", directory=str(tmp_path), download=False)[1].endswith(
        "h36m_val.json")
    assert [download.protocol(n) for n in ("h36m", "h36m_hourglass", "pascal3d_hrnet",
                                           "up3d_79kp", "cub_birds")] == [
        "h36m", "h36m", "pascal3d", "up3d", "none"]
    assert download.MD5["h36m_train.json"] == "454e2aee4cad761499265f858fe2e0ff"
    assert download.MD5["up3d_79kp_val.json"] is None
    assert download.file_url("h36m_val.json") == (
        "https://dl.fbaipublicfiles.com/c3dpo_nrsfm/h36m_val.json")
    with pytest.raises(ValueError, match="unknown release dataset 'h37m'"):
        download.dataset_files("h37m")


def test_dataset_files_downloads_both_splits(tmp_path):
    root = tmp_path / "server"
    root.mkdir()
    for split in ("train", "val"):
        (root / f"cub_birds_{split}.json").write_bytes(PAYLOAD)
    with _server(root) as url:
        paths = download.dataset_files("cub_birds", directory=str(tmp_path / "c"), base_url=url,
                                       progress=False)
    assert [os.path.basename(p) for p in paths] == ["cub_birds_train.json", "cub_birds_val.json"]
    assert all(_read(p) == PAYLOAD for p in paths)


def _read(path):
    with open(path, "rb") as f:
        return f.read()


@pytest.mark.parametrize("module", ["up3d", "h36m", "h36m_hourglass", "pascal3d",
                                    "pascal3d_hrnet", "cub_birds"])
def test_each_release_config_names_its_dataset_and_that_dataset_s_protocol(module):
    c = importlib.import_module(f"configs.{module}").get_config()
    assert c.data.source == "release"
    assert c.data.protocol == download.protocol(c.data.name)
    assert c.data.min_visible == 0
