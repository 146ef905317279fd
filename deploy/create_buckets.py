"""Create the buckets that FLEET_WARM_URL and FLEET_COLD_URL name, if missing, with versioning on.

The compose file runs this once before the depot nodes start (with a managed store the buckets are
made by whoever owns it). It waits for the store to answer: a store that is still starting is not
an error. Credentials and endpoint come from the depot's own settings (AWS_* variables,
FLEET_S3_ENDPOINT_URL, FLEET_S3_REGION), so it reaches the store exactly as the nodes will.

    python deploy/create_buckets.py [--versioning] [--wait SECONDS]
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any
from urllib.parse import urlsplit

import boto3
from botocore.config import Config
from botocore.exceptions import BotoCoreError, ClientError

# Answers meaning the bucket is there and ours: creating it again is success.
ALREADY_OURS = frozenset({"BucketAlreadyOwnedByYou"})


def bucket_names(*urls: str) -> list[str]:
    """The distinct buckets of the `s3://` URLs among `urls`, in order (file:// URLs have none)."""
    names: list[str] = []
    for url in urls:
        parts = urlsplit(url)
        if parts.scheme == "s3" and parts.netloc and parts.netloc not in names:
            names.append(parts.netloc)
    return names


def s3_client(endpoint_url: str | None, region: str | None) -> Any:
    return boto3.session.Session(region_name=region).client(
        "s3", endpoint_url=endpoint_url, config=Config(retries={"max_attempts": 1}, connect_timeout=3, read_timeout=30)
    )


def wait_for_store(client: Any, deadline: float) -> None:
    """Until the store answers a request (any S3 answer, even a refusal, means it is up)."""
    while True:
        try:
            client.list_buckets()
            return
        except ClientError:
            return  # it answered; a refusal of the credentials shows on create_bucket with its reason
        except BotoCoreError as exc:
            if time.monotonic() >= deadline:
                raise SystemExit(f"create_buckets: the object store did not answer: {exc}") from None
            time.sleep(1)


def ensure_bucket(client: Any, name: str, versioning: bool) -> str:
    """Create `name` unless it is already ours; returns what was done, for the log."""
    try:
        client.create_bucket(Bucket=name)
        done = f"created bucket {name}"
    except ClientError as exc:
        if exc.response.get("Error", {}).get("Code") not in ALREADY_OURS:
            raise
        done = f"bucket {name} already there"
    if versioning:
        client.put_bucket_versioning(Bucket=name, VersioningConfiguration={"Status": "Enabled"})
        done += ", versioning on"
    return done


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--versioning", action="store_true", help="turn object versioning on (backups)")
    parser.add_argument("--wait", type=float, default=120.0, help="seconds to wait for the store to answer")
    args = parser.parse_args(argv)

    from services.settings import load_settings  # the depot's settings, read as a node reads them

    settings = load_settings()
    names = bucket_names(settings.warm_url, settings.cold_url)
    if not names:
        print("create_buckets: FLEET_WARM_URL and FLEET_COLD_URL name no s3:// bucket: nothing to do")
        return 0
    client = s3_client(settings.s3_endpoint_url, settings.s3_region)
    wait_for_store(client, time.monotonic() + args.wait)
    for name in names:
        try:
            print(f"create_buckets: {ensure_bucket(client, name, args.versioning)}", flush=True)
        except ClientError as exc:
            error = exc.response.get("Error", {})
            print(f"create_buckets: bucket {name}: {error.get('Code')}: {error.get('Message')}", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
