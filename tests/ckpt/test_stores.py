"""The S3 request deadline's view of a body (``ftrain.ckpt.stores``): its size however botocore sends it, so that a
large upload over HTTPS, sent ``aws-chunked`` without a ``Content-Length``, gets the time its size needs."""

from __future__ import annotations

import io

from botocore.awsrequest import AWSRequest

from ftrain.ckpt.stores import SLOWEST_UPLOAD, _body_size

PART = 50 * 1024 * 1024  # s3fs's part of a large upload


def test_an_upload_gets_the_time_its_size_needs_however_its_size_is_told() -> None:
    told = AWSRequest(method="PUT", url="https://b.s3.amazonaws.com/k", headers={"Content-Length": str(PART)})
    chunked = {"Transfer-Encoding": "chunked", "Content-Encoding": "aws-chunked"}
    chunked["X-Amz-Decoded-Content-Length"] = str(PART)  # what botocore sends over HTTPS: no Content-Length
    over_https = AWSRequest(method="PUT", url="https://b.s3.amazonaws.com/k", headers=chunked)
    assert _body_size(told.prepare()) == _body_size(over_https.prepare()) == PART
    assert PART / SLOWEST_UPLOAD >= 200  # seconds: a part of a large object is not cut short at the read timeout
    stream = io.BytesIO(b"x" * 1000)
    stream.seek(10)
    for body, size in ((b"y" * 123, 123), (stream, 990)):
        request = AWSRequest(method="PUT", url="https://b.s3.amazonaws.com/k", data=body).prepare()
        del request.headers["Content-Length"]  # a body whose size only it tells
        assert _body_size(request) == size
    assert stream.tell() == 10  # read from where it stood, left there
