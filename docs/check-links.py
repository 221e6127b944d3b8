#!/usr/bin/env python3
"""Checks every relative link in the repository's Markdown files.

Scans README.md, docs/**/*.md and every other *.md of the repository (not under
a `target/` directory, not under `.git`), and checks each inline link
`[text](path)`, `[text](path#anchor)`, `[text](#anchor)` and image `![alt](path)`:

* the file or directory it names exists;
* it stays inside the repository (a path that resolves outside the repository
  root is an error, even if the file exists there);
* an `#anchor` into a Markdown file matches one of its headings, by GitHub's
  rules: lowercase, spaces to `-`, punctuation other than `-` and `_` dropped,
  a repeated heading gets `-1`, `-2`, ... (an anchor into another kind of file
  must be a line anchor such as `#L10` or `#L10-L20`).

Links to `http://`, `https://`, `mailto:` (and any other `scheme:`) are not
checked, nor links inside fenced code blocks or inline code. One kind of link
leaves the tree on purpose: the repository's own releases on GitHub,
`../../releases/latest` from the root README (`../../../releases/…` from
docs/): GitHub shows a Markdown file under `/OWNER/REPO/blob/BRANCH/`, so as
many `../` as the file's depth plus two reach `/OWNER/REPO/`. Any other
number of `../` before `releases` is an error.

Usage: python3 docs/check-links.py [REPO_ROOT]   (default: the parent of docs/)
Exit status: 0 when every link resolves, 1 when one does not (each is listed as
`file:line: link: why`), 2 on a usage error. Python 3 standard library only.
"""

import os
import re
import sys
from urllib.parse import unquote

SKIP_DIRS = {".git", "target", "node_modules", "dist"}
FENCE = re.compile(r"^ {0,3}(`{3,}|~{3,})")
HEADING = re.compile(r"^ {0,3}(#{1,6})[ \t]+(.*?)[ \t]*#*[ \t]*$")
SETEXT = re.compile(r"^ {0,3}(=+|-+)[ \t]*$")
INLINE_CODE = re.compile(r"(`+)(.+?)\1")
# [text](target) or ![alt](target); text may hold one level of brackets.
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*(<[^>]*>|[^\s()]*(?:\([^\s()]*\)[^\s()]*)*)(?:\s+(?:\"[^\"]*\"|'[^']*'|\([^)]*\)))?\s*\)")
SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*:")
HTML_ANCHOR = re.compile(r"<a\s+(?:name|id)=\"([^\"]+)\"", re.I)
LINE_ANCHOR = re.compile(r"^L\d+(-L\d+)?$")


def markdown_files(root):
    """Every *.md under root, sorted, skipping target/ and .git directories."""
    found = []
    for dirpath, dirnames, filenames in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if d not in SKIP_DIRS)
        for name in sorted(filenames):
            if name.endswith(".md"):
                found.append(os.path.join(dirpath, name))
    return found


def lines_outside_code(text):
    """(line number, line) for the lines not inside a fenced code block."""
    fence = None
    for number, line in enumerate(text.splitlines(), 1):
        m = FENCE.match(line)
        if fence is None:
            if m:
                fence = m.group(1)
                continue
            yield number, line
        elif m and m.group(1)[0] == fence[0] and len(m.group(1)) >= len(fence) \
                and line.strip() == m.group(1):
            fence = None


def heading_text(raw):
    """The text GitHub makes an anchor from: inline markup removed."""
    text = INLINE_CODE.sub(lambda m: m.group(2), raw)
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", text)  # links: their text
    text = re.sub(r"<[^>]+>", "", text)  # HTML tags
    return text


def slug(text):
    """GitHub's heading anchor: lowercase, punctuation but - and _ dropped, spaces to -."""
    text = heading_text(text).strip().lower()
    text = "".join(c for c in text if c.isalnum() or c in "-_ ")
    return text.replace(" ", "-")


def anchors_of(path, cache):
    """Every anchor a Markdown file offers (GitHub's rules, repeats numbered)."""
    if path in cache:
        return cache[path]
    with open(path, encoding="utf-8") as f:
        text = f.read()
    seen = {}
    anchors = set()
    previous = None
    for _, line in lines_outside_code(text):
        for m in HTML_ANCHOR.finditer(line):
            anchors.add(m.group(1))
        title = None
        m = HEADING.match(line)
        if m:
            title = m.group(2)
        elif previous is not None and previous.strip() and SETEXT.match(line) \
                and not HEADING.match(previous):
            title = previous.strip()
        previous = line
        if title is None:
            continue
        base = slug(title)
        n = seen.get(base, 0)
        seen[base] = n + 1
        anchors.add(base if n == 0 else f"{base}-{n}")
    cache[path] = anchors
    return anchors


def links_in(text):
    """(line number, target) of every inline link outside code."""
    for number, line in lines_outside_code(text):
        line = INLINE_CODE.sub(lambda m: " " * len(m.group(0)), line)
        for m in LINK.finditer(line):
            target = m.group(1)
            if target.startswith("<") and target.endswith(">"):
                target = target[1:-1]
            yield number, target


def check_link(source, target, root, cache):
    """None when the link resolves, else why not."""
    if not target:
        return "empty link"
    if SCHEME.match(target) or target.startswith("//"):
        return None  # http(s), mailto, ...: not checked
    path_part, _, anchor = target.partition("#")
    path_part = unquote(path_part)
    m = re.match(r"^((?:\.\./)+)releases(/[A-Za-z0-9._/-]*)?$", path_part)
    if m:
        depth = len(os.path.relpath(os.path.dirname(source), root).split(os.sep))
        depth = 0 if os.path.dirname(os.path.abspath(source)) == os.path.abspath(root) else depth
        ups = m.group(1).count("../")
        if ups == depth + 2 and not anchor:
            return None  # the repository's releases on GitHub
        return f"the repository's releases are {'../' * (depth + 2)}releases from here"
    if path_part == "":
        dest = source
    elif path_part.startswith("/"):
        dest = os.path.join(root, path_part.lstrip("/"))
    else:
        dest = os.path.join(os.path.dirname(source), path_part)
    dest = os.path.realpath(dest)
    real_root = os.path.realpath(root)
    if os.path.commonpath([dest, real_root]) != real_root:
        return "leaves the repository"
    if not os.path.exists(dest):
        return "no such file or directory"
    if anchor:
        anchor = unquote(anchor)
        if os.path.isdir(dest):
            return "an anchor on a directory"
        if dest.endswith(".md"):
            if anchor not in anchors_of(dest, cache):
                return f"no heading `#{anchor}` in {os.path.relpath(dest, real_root)}"
        elif not LINE_ANCHOR.match(anchor):
            return f"`#{anchor}` is not a line anchor (#L10) and the file is not Markdown"
    return None


def main(argv):
    if len(argv) > 2 or (len(argv) == 2 and argv[1] in ("-h", "--help")):
        print(__doc__.strip())
        return 2 if len(argv) > 2 else 0
    here = os.path.dirname(os.path.abspath(__file__))
    root = os.path.abspath(argv[1]) if len(argv) == 2 else os.path.dirname(here)
    if not os.path.isdir(root):
        print(f"check-links: {root}: not a directory", file=sys.stderr)
        return 2
    cache = {}
    checked = 0
    broken = []
    files = markdown_files(root)
    for path in files:
        with open(path, encoding="utf-8") as f:
            text = f.read()
        for number, target in links_in(text):
            if SCHEME.match(target) or target.startswith("//"):
                continue
            checked += 1
            why = check_link(path, target, root, cache)
            if why:
                broken.append(f"{os.path.relpath(path, root)}:{number}: {target}: {why}")
    for line in broken:
        print(line)
    print(f"check-links: {checked} relative links in {len(files)} Markdown files, "
          f"{len(broken)} broken")
    return 1 if broken else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
