"""An OpenAI-compatible chat endpoint whose replies are written by whoever answers a file queue.

For recording LLM exchanges with a model that has no HTTP API of its own (an assistant in a chat, an
agent, a person): MIRA talks to this server exactly as to any endpoint (``--llm openai:MODEL
--base-url http://127.0.0.1:PORT/v1``); each request's messages are written to the queue as a
readable prompt, and the request is answered once a reply file appears. The one answering sees the
prompt and nothing else, as a model behind an API would.

    python bench/llm/relay.py serve --queue Q --port 8765          # the endpoint (blocks)
    python bench/llm/relay.py next --queue Q --wait 580            # print the next unanswered prompt
    python bench/llm/relay.py answer --queue Q ID FILE             # send FILE as the reply to prompt ID
    python bench/llm/relay.py done --queue Q                       # no more prompts will come

Queue layout: ``NNNN.request.json`` (the request body), ``NNNN.prompt.md`` (its messages as text),
``NNNN.reply.txt`` (the answer), ``DONE`` (written when the client has finished).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

POLL_S = 1.0


def render(messages: list[dict[str, Any]]) -> str:
    """A conversation as text: each message under a heading with its role."""
    parts = []
    for m in messages:
        parts.append(f"===== {str(m.get('role', '?')).upper()} =====\n{m.get('content', '')}")
    return "\n\n".join(parts) + "\n\n===== (write the ASSISTANT's next message) =====\n"


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


class Queue:
    def __init__(self, root: Path) -> None:
        self.root = root
        root.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()

    def submit(self, body: dict[str, Any]) -> str:
        with self._lock:
            n = len(list(self.root.glob("*.request.json")))
            qid = f"{n:04d}"
            _write_atomic(self.root / f"{qid}.request.json", json.dumps(body, indent=1, ensure_ascii=False))
            _write_atomic(self.root / f"{qid}.prompt.md", render(body.get("messages", [])))
        return qid

    def reply(self, qid: str) -> str | None:
        path = self.root / f"{qid}.reply.txt"
        return path.read_text(encoding="utf-8") if path.is_file() else None

    def pending(self) -> list[str]:
        return sorted(p.name.split(".")[0] for p in self.root.glob("*.prompt.md")
                      if not (self.root / f"{p.name.split('.')[0]}.reply.txt").exists())


def serve(queue: Queue, port: int) -> ThreadingHTTPServer:
    class Handler(BaseHTTPRequestHandler):
        def log_message(self, format: str, *args: Any) -> None:
            pass

        def do_POST(self) -> None:
            if not self.path.rstrip("/").endswith("/chat/completions"):
                self.send_error(404)
                return
            body = json.loads(self.rfile.read(int(self.headers.get("Content-Length", "0"))) or b"{}")
            qid = queue.submit(body)
            print(f"relay: prompt {qid} queued in {queue.root}", file=sys.stderr, flush=True)
            while (content := queue.reply(qid)) is None:
                time.sleep(POLL_S)
            prompt_chars = sum(len(str(m.get("content", ""))) for m in body.get("messages", []))
            out = {
                "id": f"relay-{qid}", "object": "chat.completion", "created": int(time.time()),
                "model": body.get("model", "relay"),
                "choices": [{"index": 0, "message": {"role": "assistant", "content": content},
                             "finish_reason": "stop"}],
                # No tokenizer here: about four characters a token, an estimate for the run's token budget.
                "usage": {"prompt_tokens": prompt_chars // 4, "completion_tokens": len(content) // 4,
                          "total_tokens": (prompt_chars + len(content)) // 4},
            }
            data = json.dumps(out).encode()
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)
            print(f"relay: prompt {qid} answered", file=sys.stderr, flush=True)

    server = ThreadingHTTPServer(("127.0.0.1", port), Handler)
    server.daemon_threads = True
    return server


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("serve")
    s.add_argument("--queue", required=True, type=Path)
    s.add_argument("--port", type=int, required=True)
    n = sub.add_parser("next")
    n.add_argument("--queue", required=True, type=Path)
    n.add_argument("--wait", type=float, default=580.0, help="seconds to wait for a prompt")
    a = sub.add_parser("answer")
    a.add_argument("--queue", required=True, type=Path)
    a.add_argument("id")
    a.add_argument("file", type=Path)
    d = sub.add_parser("done")
    d.add_argument("--queue", required=True, type=Path)
    args = p.parse_args(argv)
    queue = Queue(args.queue)
    if args.cmd == "serve":
        server = serve(queue, args.port)
        print(f"relay: serving http://127.0.0.1:{args.port}/v1 for {args.queue}", file=sys.stderr, flush=True)
        server.serve_forever()
        return 0
    if args.cmd == "done":
        (args.queue / "DONE").write_text("done\n")
        return 0
    if args.cmd == "answer":
        if not (args.queue / f"{args.id}.prompt.md").is_file():
            print(f"relay: no prompt {args.id} in {args.queue}", file=sys.stderr)
            return 2
        if (args.queue / f"{args.id}.reply.txt").exists():
            print(f"relay: prompt {args.id} is already answered", file=sys.stderr)
            return 2
        _write_atomic(args.queue / f"{args.id}.reply.txt", args.file.read_text(encoding="utf-8"))
        print(f"relay: answer to prompt {args.id} sent")
        return 0
    deadline = time.monotonic() + args.wait
    while True:
        pending = queue.pending()
        if pending:
            qid = pending[0]
            print(f"PROMPT {qid}\n")
            print((args.queue / f"{qid}.prompt.md").read_text(encoding="utf-8"))
            print(f"(answer with: python bench/llm/relay.py answer --queue {args.queue} {qid} REPLY_FILE)")
            return 0
        if (args.queue / "DONE").exists():
            print("DONE: the run has finished; no more prompts will come.")
            return 3
        if time.monotonic() > deadline:
            print("NOTHING YET: no prompt arrived within the wait; call next again.")
            return 4
        time.sleep(POLL_S)


if __name__ == "__main__":
    sys.exit(main())
