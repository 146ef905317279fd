from tests.services.storage.s3_backends import s3_target, seaweed_endpoint

__all__ = ["s3_target", "seaweed_endpoint"]
