"""`skyview cache` (the cached databases) and `skyview catalog` (build or describe the guide catalog)."""

from __future__ import annotations

import json
import time
from pathlib import Path

from skyview.cli.common import EXIT_SOLVED, Parser, add_epoch, check_new_file, float_arg, method_names
from skyview.core.errors import BadInput


def cmd_catalog(a) -> int:
    from skyview.core.catalog import ASSET_PATH, build_guide_catalog, load_guide_catalog, save_guide_catalog

    if a.action == "build":
        out = Path(a.out) if a.out else ASSET_PATH
        if out.suffix != ".npz":
            raise BadInput(f"{out}: the guide catalog is written as a .npz file")
        # the shipped catalog is rebuilt in place by design; another existing file only with --force
        check_new_file(out, a.force or a.out is None)
        t0 = time.perf_counter()
        cat = build_guide_catalog(epoch=a.epoch, mag_limit=a.mag_limit)
        t1 = time.perf_counter()
        try:
            save_guide_catalog(cat, out)
        except OSError as exc:
            raise BadInput(f"cannot write {out}: {exc.strerror}") from None
        t2 = time.perf_counter()
        load_guide_catalog(out)
        t3 = time.perf_counter()
        print(f"wrote {out}: {len(cat)} stars (Hp <= {a.mag_limit:g}) at epoch {a.epoch:g}, "
              f"{out.stat().st_size / 1e6:.2f} MB; build {1e3 * (t1 - t0):.0f} ms, write {1e3 * (t2 - t1):.0f} ms, "
              f"load {1e3 * (t3 - t2):.1f} ms")
        return EXIT_SOLVED
    cat = load_guide_catalog(Path(a.path) if a.path else None)
    info = cat.describe()
    info["brighter_than"] = {m: int((cat.mag <= m).sum()) for m in (4.5, 6.0, 6.5, 7.3, 8.0)}
    print(json.dumps(info, indent=1))
    return EXIT_SOLVED


def cmd_cache(a) -> int:
    from skyview.core.catalog import cache_dir
    from skyview.identify.database import cached_databases, clear_cache

    if a.action == "clear":
        n, b = clear_cache(a.method)
        print(f"removed {n} cached database file(s), {b / 2 ** 20:.1f} MB, from {cache_dir() / 'databases'}")
        return EXIT_SOLVED
    rows = cached_databases()
    total = sum(r["bytes"] for r in rows)
    print(f"{cache_dir() / 'databases'}: {len(rows)} database(s), {total / 2 ** 20:.1f} MB "
          f"(SKYVIEW_CACHE moves it; 'skyview cache clear' empties it)")
    for r in rows:
        print(f"  {r['bytes'] / 2 ** 20:9.1f} MB  {time.strftime('%Y-%m-%d %H:%M', time.localtime(r['used']))}  "
              f"{Path(r['path']).name}")
    return EXIT_SOLVED


def add_parsers(sub) -> None:
    from skyview.core.catalog import DEFAULT_BUILD_MAG_LIMIT

    k = sub.add_parser("cache", help="list or clear the cached databases")
    ksub = k.add_subparsers(dest="action", required=True, parser_class=Parser, metavar="ACTION")
    ksub.add_parser("list", help="the cached databases, their size and last use")
    kc = ksub.add_parser("clear", help="delete the cached databases (they are rebuilt when next needed)")
    kc.add_argument("--method", default=None, metavar="NAME",
                    help=f"only this database's files: patterns (the blind database), nearest (the verification's "
                         f"table of each star's nearest neighbour) or a method "
                         f"({', '.join(method_names())})")
    k.set_defaults(func=cmd_cache)

    c = sub.add_parser("catalog", help="build or describe the guide catalog")
    csub = c.add_subparsers(dest="action", required=True, parser_class=Parser, metavar="ACTION")
    cb = csub.add_parser("build", help="derive the guide catalog from Hipparcos-2 (hip2.dat)")
    add_epoch(cb)
    cb.add_argument("--mag-limit", type=float_arg, default=DEFAULT_BUILD_MAG_LIMIT,
                    help=f"keep stars with Hp <= this, Hipparcos magnitude (default {DEFAULT_BUILD_MAG_LIMIT:g})")
    cb.add_argument("--out", default=None, help="the .npz file (default: the shipped assets/guide_catalog.npz)")
    cb.add_argument("--force", action="store_true", help="overwrite an existing --out file")
    ci = csub.add_parser("info", help="describe a guide catalog")
    ci.add_argument("path", nargs="?", help="a guide catalog .npz (default: the shipped one)")
    c.set_defaults(func=cmd_catalog)
