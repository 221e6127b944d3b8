#!/usr/bin/env bash
# Ready-made flash images, one set per board, into one folder with their
# checksums — for owners who flash without a Rust toolchain (docs/flashing.md).
#
# Usage: ./make-images.sh [OUT_DIR]            (default: target/images)
# Needs: the firmware's toolchain. The images are packed by
# host-tests/pack-images (espflash's library: byte for byte what
# `espflash save-image` writes), built here unless PACK_IMAGES names it;
# PACK_IMAGES_CROSSCHECK=espflash also runs the espflash command (4.7.0) on
# every ELF and fails unless its images are the same bytes (the release does).
# Environment: IMAGE_FEATURES — extra cargo features for every image, and
# IMAGE_SUFFIX — a name part for them (e.g. IMAGE_FEATURES=wifi IMAGE_SUFFIX=-wifi).
#
# Per board (the `board-…` features of Cargo.toml), built like its alias
# `cargo build-<board>` in .cargo/config.toml (the log path that needs only the
# board's own USB connector, the inverter output and the host link), with the
# partition table of partitions.csv (nvs, otadata, two app slots of 1728 KiB,
# the history partition):
#   tinybms-<board>.bin         bootloader + partition table + app, written at
#                               0x0: a first install (it also erases the stored
#                               configuration and otadata: it covers both)
#   tinybms-<board>-app.bin     the app alone, for ota_0 at 0x20000
#   tinybms-<board>-otadata.bin otadata erased (8 KiB of FF), for 0x10000: with
#                               the app, a reinstall by cable that keeps the
#                               configuration and boots ota_0
#   tinybms-<board>-boot.bin    the merged image's first 0x9000 bytes
#                               (bootloader and partition table, up to the nvs
#                               partition)
#   tinybms-<board>.tbu         the update file: the app signed (docs/updates.md),
#                               what `tinybms update` sends over USB or Wi-Fi
#   manifest-<board>.json       the ESP Web Tools manifest of the browser
#                               installer: boot.bin at 0x0, otadata.bin at
#                               0x10000 and app.bin at 0x20000, so an update
#                               leaves the nvs partition (the configuration) alone
# and SHA256SUMS over all of them. check-images.py checks their layout and
# the update files' signatures.
# The signing key: TINYBMS_SIGNING_KEY_FILE (a private key, 128 hex digits,
# `tinybms keygen`; the release workflow's secret); its public key is built
# into every image (TINYBMS_UPDATE_KEY). Without one, a throwaway key is made
# once in the target folder (openssl): those images trust it and no other
# bridge does (TINYBMS_SIGNING_KEY_MAKE=1: made at TINYBMS_SIGNING_KEY_FILE
# when it is missing).
# The update files are signed by `tinybms sign` (TINYBMS names the tool, else
# it is built from this repository).
# TINYBMS_VERSION (the release tag without its `v`; else the package's
# version) is the version the images report and the manifests carry.
# MAKE_IMAGES_STEP: `build` builds every board's ELF into OUT_DIR, `pack` makes
# the images, manifests and SHA256SUMS from those ELFs, `all` (the default)
# both.
# IMAGE_BOARDS="board …": only those boards (e.g. your own build of your board:
# docs/updates.md, "From source").
# IMAGE_LINT_BOARDS="board …": those boards' builds are also clippy's runs over
# the firmware crate (-D warnings; CI).
# Every image names what it was built from (`hello`'s `build`, `tinybms version`,
# its first log line, Home Assistant's device info): TINYBMS_BUILD if set (a
# release's name), else `git describe --always --dirty --tags`, else `unknown`
# (a copy outside git) — never the `dev` of a local build.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"

if [[ -z ${TINYBMS_BUILD:-} ]]; then
    TINYBMS_BUILD=$(git describe --always --dirty --tags 2>/dev/null) || TINYBMS_BUILD=unknown
    [[ -n $TINYBMS_BUILD ]] || TINYBMS_BUILD=unknown
fi
export TINYBMS_BUILD
echo "== build $TINYBMS_BUILD"

out=${1:-target/images}
mkdir -p "$out"
phase=${MAKE_IMAGES_STEP:-all}
case $phase in build | pack | all) ;; *) echo "make-images: MAKE_IMAGES_STEP is build, pack or all" >&2; exit 2 ;; esac
if [[ $phase != build ]]; then
    if [[ -z ${PACK_IMAGES:-} ]]; then
        # Its own workspace, built from its folder (this folder's cargo
        # configuration would build it for the chip).
        (cd ../host-tests/pack-images && cargo build -q --locked)
        PACK_IMAGES=$PWD/../host-tests/pack-images/target/debug/pack-images
    fi
    [[ -x $PACK_IMAGES ]] || { echo "make-images: $PACK_IMAGES is not a program" >&2; exit 2; }
    if [[ -z ${TINYBMS:-} ]]; then
        (cd .. && cargo build -q --locked -p tinybms)
        TINYBMS=$PWD/../target/debug/tinybms
    fi
    [[ -x $TINYBMS ]] || { echo "make-images: $TINYBMS is not a program" >&2; exit 2; }
    if [[ -n ${PACK_IMAGES_CROSSCHECK:-} ]]; then
        "$PACK_IMAGES_CROSSCHECK" --version | grep -qx 'espflash 4.7.0' \
            || { echo "make-images: the cross-check needs espflash 4.7.0" >&2; exit 2; }
    fi
fi

# The signing key and its public key (built into every image). A private key
# file is 128 hex digits, the seed and then its public key, with # comment
# lines (`tinybms keygen`'s format; docs/updates.md): its public half is
# checked against the seed here (openssl: a DER private key is a fixed prefix
# and the 32-byte seed; the public key's DER ends in its 32 bytes).
key_file=${TINYBMS_SIGNING_KEY_FILE:-target/update-signing-key.hex}
TINYBMS_UPDATE_KEY=$(python3 - "$key_file" <<'PY'
import os, subprocess, sys
path = sys.argv[1]
prefix = bytes.fromhex("302e020100300506032b657004220420")
def public_of(seed):
    der = subprocess.run(["openssl", "pkey", "-inform", "DER", "-pubout", "-outform", "DER"],
                         input=prefix + seed, capture_output=True, check=True).stdout
    return der[-32:]
if not os.path.exists(path) and (not os.environ.get("TINYBMS_SIGNING_KEY_FILE")
                                 or os.environ.get("TINYBMS_SIGNING_KEY_MAKE")):
    # No key given (or one to make where it is missing: CI's): a throwaway
    # one, made once.
    # Written whole, then linked into place: two builds at once make one key.
    seed = os.urandom(32)
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    tmp = "%s.%d" % (path, os.getpid())
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write("# tinybms update signing key: PRIVATE (a throwaway one of make-images.sh)\n"
                f"{seed.hex()}\n{public_of(seed).hex()}\n")
    try:
        os.link(tmp, path)
        print("== a throwaway signing key (%s): these images trust it, no other bridge does"
              % path, file=sys.stderr)
    except FileExistsError:
        pass
    finally:
        os.unlink(tmp)
text = "".join(l.strip() for l in open(path) if not l.strip().startswith("#"))
if len(text) == 64:
    sys.exit("make-images: %s holds 64 hex digits: a public key (or a private key of an older "
             "tinybms keygen); sign with a private key, 128 hex digits (tinybms keygen)" % path)
if len(text) != 128:
    sys.exit("make-images: %s is not a private key (128 hex digits, tinybms keygen)" % path)
raw = bytes.fromhex(text)
seed, public = raw[:32], raw[32:]
if public_of(seed) != public:
    sys.exit("make-images: %s is damaged: its public half is not its seed's" % path)
print(public.hex())
PY
) || { echo "make-images: cannot read the signing key $key_file" >&2; exit 2; }
export TINYBMS_UPDATE_KEY
echo "== images trust the update key $TINYBMS_UPDATE_KEY"

version=${TINYBMS_VERSION:-$(sed -n 's/^version = "\(.*\)"$/\1/p' Cargo.toml | head -n 1)}
export TINYBMS_VERSION=$version
# The name the firmware gives the installer (Improv's device info): the
# manifests must carry the same, so an installed bridge is recognised.
product=$(sed -n 's/^pub const PRODUCT: &str = "\(.*\)";$/\1/p' src/improv/mod.rs)
[[ -n $product ]] || { echo "make-images: no PRODUCT in src/improv/mod.rs" >&2; exit 2; }

boards=$(sed -n 's/^board-\([a-z0-9-]*\) = \["\(esp32c[36]\)"\]$/\1:\2/p' Cargo.toml)
[[ -n $boards ]] || { echo "make-images: no board features in Cargo.toml" >&2; exit 2; }
# IMAGE_BOARDS="board …": only those (an owner's own build for their board).
if [[ -n ${IMAGE_BOARDS:-} ]]; then
    chosen=""
    for b in $IMAGE_BOARDS; do
        entry=$(printf '%s\n' $boards | grep "^$b:" || true)
        [[ -n $entry ]] || {
            echo "make-images: no board $b (the boards: $(printf '%s ' $boards | sed 's/:[a-z0-9]*//g'))" >&2
            exit 2
        }
        chosen="$chosen $entry"
    done
    boards=$chosen
fi

for entry in $boards; do
    board=${entry%%:*}
    chip=${entry##*:}
    alias_line=$(sed -n "s/^build-$board = \"\(.*\)\"$/\1/p" .cargo/config.toml)
    [[ -n $alias_line ]] || { echo "make-images: no alias build-$board in .cargo/config.toml" >&2; exit 2; }
    case $chip in
        esp32c3) target=riscv32imc-unknown-none-elf ;;
        esp32c6) target=riscv32imac-unknown-none-elf ;;
    esac
    # The alias's arguments, with the extra features added to its --features.
    read -r -a args <<<"$alias_line"
    if [[ -n ${IMAGE_FEATURES:-} ]]; then
        for i in "${!args[@]}"; do
            if [[ ${args[$i]} == --features ]]; then
                args[$((i + 1))]="${args[$((i + 1))]},$IMAGE_FEATURES"
            fi
        done
    fi
    name="tinybms-$board${IMAGE_SUFFIX:-}"
    if [[ $phase != pack ]]; then
        echo "== $board ($chip): cargo ${args[*]}"
        if [[ " ${IMAGE_LINT_BOARDS:-} " == *" $board "* ]]; then
            # clippy over the firmware crate as part of this build (CI).
            RUSTC_WORKSPACE_WRAPPER=$(command -v clippy-driver) CLIPPY_ARGS=-Dwarnings \
                cargo "${args[@]}" --quiet
        else
            cargo "${args[@]}" --quiet
        fi
        cp "${CARGO_TARGET_DIR:-target}/$target/release/tinybms-firmware" "$out/$name.elf"
    fi
    [[ $phase != build ]] || continue
    [[ -f $out/$name.elf ]] || { echo "make-images: $out/$name.elf missing (MAKE_IMAGES_STEP=build first)" >&2; exit 2; }
    "$PACK_IMAGES" "$chip" "$out/$name.elf" "$out/$name.bin" "$out/$name-app.bin" partitions.csv >/dev/null
    if [[ -n ${PACK_IMAGES_CROSSCHECK:-} ]]; then
        x=$(mktemp -d)
        "$PACK_IMAGES_CROSSCHECK" save-image --chip "$chip" --merge --skip-padding --partition-table partitions.csv "$out/$name.elf" "$x/m.bin" >/dev/null
        "$PACK_IMAGES_CROSSCHECK" save-image --chip "$chip" --partition-table partitions.csv "$out/$name.elf" "$x/a.bin" >/dev/null
        cmp "$x/m.bin" "$out/$name.bin" && cmp "$x/a.bin" "$out/$name-app.bin" \
            || { echo "make-images: $name: not espflash's bytes" >&2; exit 1; }
        rm -rf "$x"
        echo "== $name: the same bytes as espflash save-image"
    fi
    head -c $((0x9000)) "$out/$name.bin" > "$out/$name-boot.bin"
    head -c $((0x2000)) /dev/zero | tr '\0' '\377' > "$out/$name-otadata.bin"
    # What the image has built in, as its hello names it.
    features=can,host-link
    [[ ,${IMAGE_FEATURES:-}, == *,wifi,* ]] && features+=,wifi
    features+=,store
    "$TINYBMS" sign --key "$key_file" --chip "$chip" --board "$board" --version "$version" \
        --features "$features" --build "$TINYBMS_BUILD" "$out/$name-app.bin" -o "$out/$name.tbu" >/dev/null
    case $chip in
        esp32c3) family=ESP32-C3 ;;
        esp32c6) family=ESP32-C6 ;;
    esac
    cat > "$out/manifest-$board${IMAGE_SUFFIX:-}.json" <<MANIFEST
{
  "name": "$product",
  "version": "$version$([[ ,${IMAGE_FEATURES:-}, == *,wifi,* ]] && echo +wifi)",
  "board": "$board",
  "wifi": $([[ ,${IMAGE_FEATURES:-}, == *,wifi,* ]] && echo true || echo false),
  "new_install_prompt_erase": false,
  "new_install_improv_wait_time": 15,
  "builds": [
    {
      "chipFamily": "$family",
      "parts": [
        { "path": "$name-boot.bin", "offset": 0 },
        { "path": "$name-otadata.bin", "offset": 65536 },
        { "path": "$name-app.bin", "offset": 131072 }
      ]
    }
  ]
}
MANIFEST
done

if [[ $phase == build ]]; then
    echo "== ELFs in $out"
    exit 0
fi
(cd "$out" && sha256sum -- *.bin *.tbu > SHA256SUMS)
echo "$TINYBMS_UPDATE_KEY" > "$out/update-key.pub"
echo "== images in $out"
(cd "$out" && ls -l -- *.bin *.tbu && cat SHA256SUMS)
