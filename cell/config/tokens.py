"""API token rules, checked with the rest of the config before any hardware is touched.

On a cell with any real device the sample tokens are refused, and so are weak ones: shorter
than ``MIN_TOKEN_LENGTH``, with white space at either end (a copy-paste slip that makes the
token something other than what the operator types), or with less than ``MIN_TOKEN_BITS`` of
character entropy (``"aaaaaaaaaaaaaaaa"``). ``python -c 'import secrets;
print(secrets.token_urlsafe(32))'`` makes a good one.
"""

from __future__ import annotations

import math
from collections import Counter

from cell.config.schema import SAMPLE_OPCUA_PASSWORDS, SAMPLE_TOKENS, CellConfig

MIN_TOKEN_LENGTH = 16
MIN_TOKEN_BITS = 48.0


def token_bits(token: str) -> float:
    """Empirical Shannon entropy of the token's characters times its length."""
    n = len(token)
    if n == 0:
        return 0.0
    counts = Counter(token)
    per_char = -sum(c / n * math.log2(c / n) for c in counts.values())
    return per_char * n


def token_problems(config: CellConfig, simulated: bool) -> list[str]:
    """Every reason the configured tokens are not acceptable (empty: fine)."""
    if simulated:
        return []
    problems = []
    for k, t in enumerate(config.api.tokens):
        key = f"api.tokens[{k}] ({t.name or t.role})"
        if t.sha256:
            if len(t.salt) < 8:
                problems.append(f"{key}: a hashed token needs a salt of at least 8 characters")
            continue  # the token itself is not here to judge; its hash is
        if t.token in SAMPLE_TOKENS:
            problems.append(f"{key}: the sample token {t.token!r} is not allowed with real "
                            "hardware; set your own secret token")
        elif t.token != t.token.strip():
            problems.append(f"{key}: the token starts or ends with white space")
        elif len(t.token) < MIN_TOKEN_LENGTH:
            problems.append(f"{key}: the token has {len(t.token)} characters; at least "
                            f"{MIN_TOKEN_LENGTH} are needed on real hardware")
        elif token_bits(t.token) < MIN_TOKEN_BITS:
            problems.append(f"{key}: the token is too predictable ({token_bits(t.token):.0f} "
                            f"bits of character entropy, at least {MIN_TOKEN_BITS:.0f} needed)")
    problems.extend(interface_problems(config))
    return problems


def interface_problems(config: CellConfig) -> list[str]:
    """The PLC and robot-program interfaces on real hardware: no sample OPC UA passwords, and
    the XML-RPC endpoint only with a token in its URL."""
    problems = []
    if config.opcua.enabled:
        for k, u in enumerate(config.opcua.users):
            if u.password in SAMPLE_OPCUA_PASSWORDS or len(u.password) < MIN_TOKEN_LENGTH:
                problems.append(f"opcua.users[{k}] ({u.name}): the password is a sample or "
                                f"shorter than {MIN_TOKEN_LENGTH} characters; set your own")
    if config.urscript.xmlrpc_port and not config.urscript.require_token:
        problems.append("urscript.require_token: the XML-RPC endpoint needs a token in its URL "
                        "on real hardware (http://HOST:PORT/<token>/RPC2)")
    return problems
