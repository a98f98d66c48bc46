"""A tiny OpenAI-compatible chat server for tests: real HTTP on 127.0.0.1, scripted behaviours.

Tests queue behaviours (a good reply, an HTTP error with headers, a hang, a raw body) and the server
answers successive ``POST /v1/chat/completions`` with them, recording every request it receives,
so a test can count exactly how many requests reached the wire. Nothing leaves the machine.
"""

from __future__ import annotations

import json
import threading
from collections import deque
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any


@dataclass
class Behaviour:
    """What the server does for one request."""

    kind: str  # "reply" | "status" | "hang" | "raw"
    content: str = ""
    status: int = 200
    headers: dict[str, str] = field(default_factory=dict)
    body: bytes | None = None
    seconds: float = 0.0
    prompt_tokens: int = 11
    completion_tokens: int = 7


def reply(content: str, *, prompt_tokens: int = 11, completion_tokens: int = 7) -> Behaviour:
    return Behaviour(
        "reply", content=content, prompt_tokens=prompt_tokens, completion_tokens=completion_tokens
    )


def status(code: int, *, headers: dict[str, str] | None = None, message: str = "scripted error") -> Behaviour:
    body = json.dumps({"error": {"message": message, "type": "test", "code": str(code)}}).encode()
    return Behaviour("status", status=code, headers=headers or {}, body=body)


def hang(seconds: float) -> Behaviour:
    return Behaviour("hang", seconds=seconds)


def raw(body: bytes, *, code: int = 200) -> Behaviour:
    return Behaviour("raw", status=code, body=body)


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    block_on_close = False
    owner: ChatServer


class _Handler(BaseHTTPRequestHandler):
    server: _Server

    def log_message(self, format: str, *args: Any) -> None:  # silence the default stderr log
        pass

    def _send(self, code: int, body: bytes, headers: dict[str, str] | None = None) -> None:
        self.send_response(code)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        for key, value in (headers or {}).items():
            self.send_header(key, value)
        self.end_headers()
        self.wfile.write(body)

    def do_POST(self) -> None:
        owner = self.server.owner
        length = int(self.headers.get("Content-Length") or 0)
        payload = self.rfile.read(length)
        try:
            parsed: Any = json.loads(payload)
        except json.JSONDecodeError:
            parsed = None
        with owner.lock:
            owner.requests.append(
                {
                    "path": self.path,
                    "json": parsed,
                    "headers": {k.lower(): v for k, v in self.headers.items()},
                }
            )
            behaviour = owner.queue.popleft() if owner.queue else None
        if self.path != "/v1/chat/completions":
            self._send(404, b'{"error": {"message": "not found"}}')
            return
        if behaviour is None:
            self._send(500, b'{"error": {"message": "chat_server: no scripted behaviour left"}}')
            return
        try:
            if behaviour.kind == "hang":
                owner.stopping.wait(behaviour.seconds)
                self._send(200, _completion("too late", parsed))
            elif behaviour.kind == "reply":
                self._send(200, _completion(behaviour.content, parsed, behaviour))
            else:
                self._send(behaviour.status, behaviour.body or b"", behaviour.headers)
        except (BrokenPipeError, ConnectionResetError):
            pass  # the client gave up (timeout test)


def _completion(content: str, request: Any, b: Behaviour | None = None) -> bytes:
    model = request.get("model", "test-model") if isinstance(request, dict) else "test-model"
    prompt, completion = (b.prompt_tokens, b.completion_tokens) if b is not None else (1, 1)
    return json.dumps(
        {
            "id": "chatcmpl-test",
            "object": "chat.completion",
            "created": 0,
            "model": model,
            "choices": [
                {"index": 0, "message": {"role": "assistant", "content": content}, "finish_reason": "stop"}
            ],
            "usage": {
                "prompt_tokens": prompt,
                "completion_tokens": completion,
                "total_tokens": prompt + completion,
            },
        }
    ).encode()


class ChatServer:
    """``with ChatServer() as srv: srv.push(reply("hi")); ... srv.url ...``"""

    def __init__(self) -> None:
        self.queue: deque[Behaviour] = deque()
        self.requests: list[dict[str, Any]] = []
        self.lock = threading.Lock()
        self.stopping = threading.Event()
        self._httpd = _Server(("127.0.0.1", 0), _Handler)
        self._httpd.owner = self
        self._thread = threading.Thread(target=self._httpd.serve_forever, kwargs={"poll_interval": 0.05})
        self._thread.daemon = True

    @property
    def url(self) -> str:
        host, port = self._httpd.server_address[:2]
        return f"http://{host!s}:{port}/v1"

    def push(self, *behaviours: Behaviour) -> None:
        with self.lock:
            self.queue.extend(behaviours)

    @property
    def count(self) -> int:
        with self.lock:
            return len(self.requests)

    def __enter__(self) -> ChatServer:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stopping.set()
        self._httpd.shutdown()
        self._httpd.server_close()
        self._thread.join(timeout=5)
