"""Schemathesis hooks for the geocal daemon (SCHEMATHESIS_HOOKS=geocal_hooks).

`POST /v1/jobs` takes a plan configuration as `application/toml`, which schemathesis has no
serializer for: the document describes the body as a string, so the generated string is sent
as its UTF-8 bytes, as a client would send a TOML file.
"""
import schemathesis


@schemathesis.serializer("application/toml")
def toml_text(ctx, value):
    if isinstance(value, bytes):
        return value
    if isinstance(value, str):
        return value.encode("utf-8")
    # Negative data may be a non-string: send its text, which is no valid plan either.
    return str(value).encode("utf-8")
