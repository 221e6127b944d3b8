#!/usr/bin/env python3
"""Gives a fresh clone's files the modification times they had in the previous
CI run on this machine, where their content is the same, so that cargo's
fingerprints (which compare modification times) rebuild only what changed.

Usage: mtimes.py RECORD   (at the clone's root)

RECORD (in the CI cache, outside the clone) lists every tracked file of the
previous run: its blob id (git's hash of the content), its modification time in
nanoseconds and its path. A file whose path and blob id are in RECORD gets the
time recorded there; any other file keeps the time the clone gave it (now), so
cargo sees it as changed. RECORD is then rewritten with this clone's files and
times. Sound by construction: a restored time always belongs to the same bytes,
as cargo saw them in the previous run; a changed file is never given an old
time, nor is a file whose working copy differs from the index. Symbolic links
and submodules are left alone.
"""
import os
import subprocess
import sys


def tracked():
    """(blob, path) of every regular tracked file."""
    out = subprocess.run(["git", "ls-files", "-s", "-z"], check=True,
                         capture_output=True).stdout
    for entry in out.split(b"\0"):
        if not entry:
            continue
        meta, path = entry.split(b"\t", 1)
        mode, blob, _stage = meta.split(b" ")
        if mode in (b"100644", b"100755"):
            yield blob.decode(), os.fsdecode(path)


def edited():
    """Tracked files whose working copy differs from the index (a local run
    with changes not staged): their blob id is not their content."""
    out = subprocess.run(["git", "diff", "--name-only", "-z"], check=True,
                         capture_output=True).stdout
    return {os.fsdecode(p) for p in out.split(b"\0") if p}


def load(record):
    known = {}
    try:
        with open(record, encoding="utf-8") as f:
            for line in f:
                parts = line.rstrip("\n").split("\t", 2)
                if len(parts) == 3 and parts[1].isdigit():
                    known[parts[2]] = (parts[0], int(parts[1]))
    except FileNotFoundError:
        pass
    return known


def main():
    if len(sys.argv) != 2:
        sys.exit("usage: mtimes.py RECORD")
    record = sys.argv[1]
    known = load(record)
    dirty = edited()
    restored = changed = 0
    lines = []
    for blob, path in tracked():
        before = known.get(path)
        if before is not None and before[0] == blob and path not in dirty:
            os.utime(path, ns=(before[1], before[1]), follow_symlinks=False)
            restored += 1
        else:
            changed += 1
        lines.append(f"{blob}\t{os.lstat(path).st_mtime_ns}\t{path}\n")
    tmp = record + ".new"
    with open(tmp, "w", encoding="utf-8") as f:
        f.writelines(lines)
    os.replace(tmp, record)
    print(f"{restored} files as in the previous run (their times restored), "
          f"{changed} new or changed")


if __name__ == "__main__":
    main()
