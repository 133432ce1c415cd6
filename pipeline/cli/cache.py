"""``iristac cache ls|verify|gc|clear``: inspect and maintain the stage store.

Each subcommand calls one :class:`pipeline.base.store.StageStore` method.
"""

from __future__ import annotations

import sys

from pipeline.cli._common import add_json_flag, make_group, print_json


def register(sub, name, help_text):
    _, group = make_group(sub, name, help_text)
    specs = [
        ("ls", "list the entries of the store", _ls),
        ("verify", "fully read and validate every entry; exit 1 and a line per bad entry", _verify),
        ("gc", "remove temporary files left by crashed writers", _gc),
        ("clear", "remove every entry (or one stage's) from the store", _clear),
    ]
    for cmd, text, func in specs:
        p = group.add_parser(cmd, help=text, description=text)
        p.add_argument("--cache", metavar="DIR", help="store folder (default: $IRISTAC_CACHE or ./iristac-cache)")
        add_json_flag(p)
        if cmd == "clear":
            p.add_argument("--stage", help="only this stage's entries")
        p.set_defaults(func=func)


def _store(args):
    from pipeline.base.store import StageStore

    return StageStore(args.cache)


def _entry_json(e):
    return {"path": str(e.path), "stage": e.stage, "kind": e.kind, "size": e.size, "schema": e.schema,
            "key": e.key, "created": e.created, "problem": e.problem}


def _ls(args) -> int:
    store = _store(args)
    entries = store.entries()
    if args.json:
        print_json({"root": str(store.root), "entries": [_entry_json(e) for e in entries]})
        return 0
    if not entries:
        print(f"{store.root}: empty")
        return 0
    print(f"{'stage':<12} {'key':<32} {'schema':<13} {'size':>10}  {'created':<25} status")
    for e in entries:
        status = e.problem and f"BAD: {e.problem}" or e.kind
        print(f"{e.stage:<12} {(e.key or e.path.name):<32} {(e.schema or '-'):<13} {e.size:>10}  "
              f"{(e.created or '-'):<25} {status}")
    return 0


def _verify(args) -> int:
    store = _store(args)
    entries = [e for e in store.entries(check=True) if e.kind == "entry"]
    bad = [e for e in entries if e.problem]
    if args.json:
        print_json({"root": str(store.root), "checked": len(entries), "bad": [_entry_json(e) for e in bad]})
    else:
        for e in bad:
            print(f"BAD {e.path}: {e.problem}")
        print(f"{len(entries)} entries checked, {len(bad)} bad", file=sys.stderr)
    return 1 if bad else 0


def _gc(args) -> int:
    removed = _store(args).gc()
    if args.json:
        print_json({"removed": [str(p) for p in removed]})
    else:
        for p in removed:
            print(f"removed {p}")
        print(f"{len(removed)} temporary files removed", file=sys.stderr)
    return 0


def _clear(args) -> int:
    removed = _store(args).clear(stage=args.stage)
    if args.json:
        print_json({"removed": [str(p) for p in removed]})
    else:
        print(f"{len(removed)} files removed", file=sys.stderr)
    return 0
