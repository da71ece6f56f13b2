"""A real S3 server on loopback for Isovox's object-store tests and benchmarks: moto's S3
implementation, served one request at a time.

Why one at a time: moto checks a conditional PUT (If-Match / If-None-Match) and then stores the
object in two steps; under werkzeug's threaded server two PUTs carrying the same ETag could both
pass the check. Served in turn, each conditional PUT is a compare-and-swap, as on S3 itself.

Usage: python s3-server.py PORT [BUCKET ...]   (prints "ready" once the buckets exist)
"""

import sys
import threading
import time

import boto3
from moto.moto_server.werkzeug_app import DomainDispatcherApplication, create_backend_app
from werkzeug.serving import make_server


def main():
    port = int(sys.argv[1])
    buckets = sys.argv[2:]
    app = DomainDispatcherApplication(create_backend_app)
    server = make_server("127.0.0.1", port, app, threaded=False)
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
