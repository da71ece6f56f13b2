"""A real S3 server on loopback for Isovox's object-store tests and benchmarks: moto's S3
implementation, served one request at a time.

Why one at a time: moto checks a conditional PUT (If-Match / If-None-Match) and then stores the
object in two steps; under werkzeug's threaded server two PUTs carrying the same ETag can both
pass the check. Serving requests in turn makes each conditional PUT a compare-and-swap, as it is
on S3 itself. Usage: python s3-server.py PORT
"""

import sys

from moto.moto_server.werkzeug_app import DomainDispatcherApplication, create_backend_app
from werkzeug.serving import run_simple

if __name__ == "__main__":
    port = int(sys.argv[1]) if len(sys.argv) > 1 else 9000
    app = DomainDispatcherApplication(create_backend_app)
    run_simple("127.0.0.1", port, app, threaded=False)
