#!/usr/bin/env bash
# Prints the section of docs/changelog.md for VERSION (`## VERSION …` up to the
# next `## `): a release's notes for owners. Exit status 1 (and a line on
# stderr) when the changelog has no such section: a release without notes
# is not made.
# usage: .github/changelog-section.sh VERSION [CHANGELOG]
set -euo pipefail
version=$1
file=${2:-"$(dirname "$0")/../docs/changelog.md"}
section=$(awk -v v="$version" '
    /^## / { inside = ($2 == v); next }
    inside { print }
' "$file")
if [[ -z ${section//[[:space:]]/} ]]; then
    echo "changelog-section: no \"## $version\" section in $file" >&2
    exit 1
fi
printf '%s\n' "$section" | sed -e '/./,$!d'
