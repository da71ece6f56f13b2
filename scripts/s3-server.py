"""A real S3 server on loopback for Isovox's object-store tests and benchmarks: moto's S3
implementation, answering one request at a time.

Why one at a time: moto checks a conditional PUT (If-Match / If-None-Match) and then stores the
object in two steps; with two requests in moto at once, two PUTs carrying the same ETag could
both pass the check. Answered in turn, each conditional PUT is a compare-and-swap, as on S3
itself.

Why a thread per connection all the same: a server that also *reads* one connection at a time
waits on whichever it accepted first. A client that opens a connection and sends nothing on it
(a request cancelled between connect and send, a keep-alive connection left idle in a pool)
stalled every other client behind it: a benchmark replica's store requests, and with them its
/metrics, hung for minutes while 128 connections waited in the accept queue. Each connection is
now read on its own thread, with a timeout, and only the call into moto is taken in turn.

Usage: python s3-server.py PORT [BUCKET ...]   (prints "ready" once the buckets exist)
"""

import sys
import threading
import time

import boto3
from moto.moto_server.werkzeug_app import DomainDispatcherApplication, create_backend_app
from werkzeug.serving import WSGIRequestHandler, make_server

# Seconds a connection may stay silent before its thread gives up on it.
IDLE_TIMEOUT = 30


class Handler(WSGIRequestHandler):
    timeout = IDLE_TIMEOUT


def one_at_a_time(app):
    """`app`, called by one request at a time (see the module's documentation)."""
    lock = threading.Lock()

    def serialized(environ, start_response):
        with lock:
            # The whole answer is made under the lock: moto's bodies are in memory.
            return list(app(environ, start_response))

    return serialized


def main():
    port = int(sys.argv[1])
    buckets = sys.argv[2:]
    app = one_at_a_time(DomainDispatcherApplication(create_backend_app))
    server = make_server("127.0.0.1", port, app, threaded=True, request_handler=Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    s3 = boto3.client(
        "s3",
        endpoint_url=f"http://127.0.0.1:{port}",
        aws_access_key_id="isovox",
        aws_secret_access_key="isovox-secret",
        region_name="us-east-1",
    )
    for bucket in buckets:
        s3.create_bucket(Bucket=bucket)
    print("ready", flush=True)
    while True:
        time.sleep(3600)


if __name__ == "__main__":
    main()
