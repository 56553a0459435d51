#!/bin/sh
# The `ps-lab` command for a clone: a link ~/.local/bin/ps-lab -> this clone's .venv/bin/ps-lab.
#
#   tools/launcher.sh link   TARGET   make it (the Makefile's install step), then say how to run ps-lab
#   tools/launcher.sh check  TARGET   say how to run ps-lab (the end of `make demo`)
#   tools/launcher.sh unlink TARGET   remove it if it points at TARGET (`make clean`)
#
# TARGET is the absolute path of .venv/bin/ps-lab. A `ps-lab` in ~/.local/bin that is not a link
# to TARGET (another clone's, a pip --user install, a script) is never replaced or removed.
# Debian and Ubuntu put ~/.local/bin on PATH in ~/.profile when it exists, i.e. from the next
# login; until then, or elsewhere, the line printed by `check` says what to type.
set -eu

action=${1:?usage: tools/launcher.sh link|check|unlink TARGET}
target=${2:?usage: tools/launcher.sh link|check|unlink TARGET}
dir="$HOME/.local/bin"
link="$dir/ps-lab"
venv=$(dirname "$(dirname "$target")")

ours() {
    [ -L "$link" ] && [ "$(readlink "$link")" = "$target" ]
}

check() {
    if ours; then
        found=$(command -v ps-lab 2>/dev/null || true)
        if [ "$found" = "$link" ]; then
            echo "ps-lab: $link -> $target"
        elif [ -n "$found" ]; then
            echo "ps-lab: $found comes first on PATH; to run this clone's: source $venv/bin/activate"
        else
            echo "ps-lab: $link, but $dir is not on PATH in this shell (new login shells on" \
                "Debian/Ubuntu add it): export PATH=\"\$HOME/.local/bin:\$PATH\"" \
                "(or: source $venv/bin/activate)"
        fi
    elif [ -e "$link" ] || [ -L "$link" ]; then
        other=$( [ -L "$link" ] && readlink "$link" || echo "not a link" )
        echo "ps-lab: $link is another ps-lab ($other), left as it is; for this clone's:" \
            "source $venv/bin/activate (or run $target)"
    else
        echo "ps-lab: no launcher in $dir; for this clone's: source $venv/bin/activate" \
            "(or run $target)"
    fi
}

case "$action" in
link)
    if [ ! -e "$link" ] && [ ! -L "$link" ]; then
        mkdir -p "$dir"
        ln -s "$target" "$link"
        echo "linked $link -> $target"
    fi
    check
    ;;
check)
    check
    ;;
unlink)
    if ours; then
        rm -f "$link"
        echo "removed $link (it pointed into $venv)"
    fi
    ;;
*)
    echo "usage: tools/launcher.sh link|check|unlink TARGET" >&2
    exit 2
    ;;
esac
