"""``vlp keys create|list|revoke``: API keys of a running service (admin)."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from app.client import VLPClient

    from ._output import Output

__all__ = ["add_keys_command"]


def _create(client: VLPClient, out: Output, args: argparse.Namespace) -> int:
    created = client.create_key(args.role, args.label)

    def render(_value: Any) -> None:
        out.console.print(
            f"{created.role} key {created.id} ({created.label}); the key, shown only now:",
            markup=False,
        )
        out.console.print(created.key, markup=False)

    out.result(created, render)
    return 0


def _list(client: VLPClient, out: Output, _args: argparse.Namespace) -> int:
    keys = client.list_keys()
    rows = [
        [
            key.id,
            key.role,
            key.source,
            key.label,
            key.created_at.isoformat(timespec="seconds"),
            key.last_used_at.isoformat(timespec="seconds") if key.last_used_at else "-",
        ]
        for key in keys.items
    ]
    columns = ["id", "role", "source", "label", "created", "last used"]
    out.result(keys, lambda _value: out.table("API keys in force", columns, rows))
    return 0


def _revoke(client: VLPClient, out: Output, args: argparse.Namespace) -> int:
    client.revoke_key(args.key_id)
    out.result({"revoked": args.key_id}, lambda _v: out.console.print(f"revoked {args.key_id}"))
    return 0


def add_keys_command(commands: Any, remote: Any) -> None:
    """Add ``keys`` with its sub-commands; ``remote(parent, name, handler, help)`` adds one."""
    keys = commands.add_parser("keys", help="API keys of a running service (admin)")
    sub = keys.add_subparsers(dest="keys_command", required=True)
    create = remote(sub, "create", _create, "create a key (its secret is printed only now)")
    create.add_argument("--role", choices=("admin", "terminal"), required=True)
    create.add_argument("--label", required=True, help="who or what holds the key")
    remote(sub, "list", _list, "list the keys in force (never their secrets)")
    remote(sub, "revoke", _revoke, "revoke a key by its id").add_argument("key_id")
