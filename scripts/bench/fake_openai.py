"""A loopback OpenAI-compatible server for `scripts/bench-infer.sh`: answers every chat
completion at once with one of three typical dashcam answers (picked by the requested model),
so a /v1/infer benchmark measures vlmfuse's own stages and not a VLM. Standard library only.

    python3 fake_openai.py PORT
"""
import json
import sys
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

ANSWERS = [
    "The car ahead brakes at the junction, so we slow down and keep a safe distance.",
    "A pedestrian crossing is ahead and the light is red: stop and yield to the pedestrians.",
    "The road is clear and dry; continue to drive as normal and check the blind spot before merging.",
]


class Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"

    def log_message(self, *args):
        pass

    def _send(self, status, body):
        data = json.dumps(body).encode()
        self.send_response(status)
        self.send_header("content-type", "application/json")
        self.send_header("content-length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def do_GET(self):
        self._send(200, {"object": "list", "data": [{"id": f"m{i}"} for i in range(3)]})

    def do_POST(self):
        n = int(self.headers.get("content-length", "0"))
        req = json.loads(self.rfile.read(n) or b"{}")
        model = str(req.get("model", "m0"))
        answer = ANSWERS[sum(map(ord, model)) % len(ANSWERS)]
        self._send(200, {
            "id": "bench", "object": "chat.completion", "model": model,
            "choices": [{"index": 0, "finish_reason": "stop",
                         "message": {"role": "assistant", "content": answer}}],
        })


if __name__ == "__main__":
    ThreadingHTTPServer(("127.0.0.1", int(sys.argv[1])), Handler).serve_forever()
