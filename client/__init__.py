"""Python SDK of the joint-limit constitution service."""
