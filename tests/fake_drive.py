"""A fake Google Drive on 127.0.0.1, well-behaved or hostile, for the download tests.

It answers as Drive does for a large file: ``/uc?export=download&id=ID`` gives a one-line
HTML confirmation page (a ``download-form`` whose action and hidden fields make the
download address), and only that address, with the page's hidden ``confirm`` and ``uuid``
values, gives the file. gdown reads the page; ``TAPTR_DRIVE_URL`` (the testing hook of
`taptr.weights.drive_download`) points taptr at the fake. Misbehaviours, each an option:
cut the transfer short, answer late, trickle the file a byte at a time, send far more than the file
(with its size declared, or without), serve a web page or Drive's quota page instead of it.
"""

from __future__ import annotations

import contextlib
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

R18_ID = "1frPX9R_nKDG8FmL-vH6l_2HsJfhvEjtg"
R50_ID = "19iql2VTqGIeoyg_wt3JjpohszN5UE6s1"
UUID = "5e1f-fake-uuid"
BLOCK = 64 * 1024


class FakeDrive:
    """Serves ``content`` behind Drive's confirmation page and records every request.

    Args:
        content: the file's bytes.
        cut_at: send only this many bytes after announcing them all, then hang up.
        kind: the file's Content-Type (``text/html`` makes it an error page).
        quota: answer with Drive's download-quota page instead of the confirmation.
        direct: serve the file at once, as Drive does for files it can scan (small ones).
        ids: the file ids it knows.
        late: seconds it waits before answering any request.
        trickle: seconds between single bytes of the file, for ``trickle_for`` seconds;
            then the rest at once (a bound, so that code that waits still ends).
        trickle_for: how long it trickles.
        padding: zeros sent after the content, until the client hangs up.
        announce: whether the file's size (content and padding) is declared.
    """

    def __init__(
        self,
        content: bytes,
        cut_at: int | None = None,
        kind: str = "",
        quota: bool = False,
        direct: bool = False,
        ids: tuple[str, ...] = (R18_ID, R50_ID),
        late: float = 0.0,
        trickle: float | None = None,
        trickle_for: float = 5.0,
        padding: int = 0,
        announce: bool = True,
    ) -> None:
        self.content, self.cut_at, self.quota, self.direct = content, cut_at, quota, direct
        self.kind = kind or "application/octet-stream"
        self.ids, self.late, self.trickle, self.trickle_for = ids, late, trickle, trickle_for
        self.padding, self.announce = padding, announce
        self.requests: list[str] = []
        self.sent = 0
        self.closing = threading.Event()
        self.server = ThreadingHTTPServer(("127.0.0.1", 0), _handler(self))
        self.server.daemon_threads = True
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        # polled often: shutdown waits for the next poll, and every test closes a server
        threading.Thread(
            target=self.server.serve_forever, kwargs={"poll_interval": 0.02}, daemon=True
        ).start()

    def page(self, file_id: str) -> str:
        """Drive's virus-scan warning for a large file, on one line as Drive sends it."""
        if self.quota:
            return (
                "<!DOCTYPE html><html><head><title>Google Drive - Quota exceeded</title></head>"
                '<body><p class="uc-error-caption">Sorry, you can&#39;t view or download this '
                'file at this time.</p><p class="uc-error-subcaption">Too many users have '
                "viewed or downloaded this file recently.</p></body></html>"
            )
        fields = {"id": file_id, "export": "download", "confirm": "t", "uuid": UUID}
        hidden = "".join(f'<input type="hidden" name="{k}" value="{v}">' for k, v in fields.items())
        return (
            "<!DOCTYPE html><html><head><title>Google Drive - Virus scan warning</title></head>"
            "<body><p>Google Drive can't scan this file for viruses.</p>"
            f'<form id="download-form" action="{self.url}/download" method="get">'
            f'<input type="submit" value="Download anyway">{hidden}</form></body></html>'
        )

    def body(self, write) -> None:
        """Writes the file's bytes as the options say, until done, cut or closing."""
        data = self.content[: self.cut_at]
        if self.trickle is not None:
            until = time.monotonic() + self.trickle_for
            while data and time.monotonic() < until:
                if self.closing.wait(self.trickle):
                    return
                write(data[:1])
                data = data[1:]
        write(data)
        left = self.padding
        while left > 0 and not self.closing.is_set():
            write(bytes(min(BLOCK, left)))
            left -= BLOCK

    def close(self) -> None:
        self.closing.set()
        self.server.shutdown()
        self.server.server_close()


def _handler(fake: FakeDrive) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        def do_GET(self):
            url = urlsplit(self.path)
            query = {k: v[0] for k, v in parse_qs(url.query).items()}
            fake.requests.append(url.path)
            if fake.late and fake.closing.wait(fake.late):
                return
            if url.path == "/uc" and fake.direct:
                self._file()
            elif url.path == "/uc" and query.get("id") in fake.ids:
                self._send(200, "text/html; charset=utf-8", fake.page(query["id"]).encode())
            elif url.path == "/download" and query.get("confirm") == "t":
                if query.get("uuid") != UUID:
                    self._send(403, "text/plain", b"no uuid")
                else:
                    self._file()
            else:
                self._send(404, "text/plain", b"not found")

        def _send(self, status: int, kind: str, body: bytes) -> None:
            self.send_response(status)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def _file(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", fake.kind)
            self.send_header("Content-Disposition", 'attachment; filename="weights.pth"')
            if fake.announce:
                # a cut transfer announces the whole file, then hangs up early
                self.send_header("Content-Length", str(len(fake.content) + fake.padding))
            self.end_headers()
            self.close_connection = True
            with contextlib.suppress(OSError):  # the client hung up, as a refusal does
                fake.body(self._write)

        def _write(self, data: bytes) -> None:
            self.wfile.write(data)
            self.wfile.flush()
            fake.sent += len(data)

        def log_message(self, *args):
            pass

    return Handler


def files_in(folder: Path) -> list[str]:
    """The names in a weights folder, sorted; none when it does not exist."""
    return sorted(p.name for p in folder.iterdir()) if folder.exists() else []
