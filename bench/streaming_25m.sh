#!/usr/bin/env bash
# A 25-million-sample capture of the default plan, MCAP CDR and one labelled CSV file,
# `rotcal run` block by block (the default) and read whole ([run] stream_above_samples
# past the capture), each under /usr/bin/time -v in turn; then every Parquet table of the
# two runs compared (bench/compare_outputs.py). docs/measured.md, "Capture formats and
# the block path", quotes its figures. About 4 GB of memory for the CSV read whole and
# 3 GB of disk in DIR.
#   bench/streaming_25m.sh DIR [ROTCAL]
set -euo pipefail
dir=${1:?usage: bench/streaming_25m.sh DIR [ROTCAL]}
rotcal=${2:-rotcal}
here=$(cd "$(dirname "$0")" && pwd)
python=$(dirname "$(command -v "$rotcal")")/python  # the interpreter rotcal runs on (polars)
mkdir -p "$dir" && cd "$dir"
rm -rf mcap csvparts csv out_*
"$rotcal" simulate mcap --format mcap-cdr --plan rotation_samples=2083258 --seed 1 >/dev/null
"$rotcal" simulate csvparts --plan rotation_samples=2083258 --seed 1 >/dev/null
mkdir -p csv && cp csvparts/dataset.toml csv/
# the plan's segment files joined into one capture: the first header, every row in plan order
first=1
for f in csvparts/*.csv; do
    if ((first)); then cat "$f"; first=0; else tail -n +2 "$f"; fi
done > csv/capture.csv
rm -rf csvparts
printf '[run]\nstream_above_samples = 10000000000\n' > whole.toml
for fmt in mcap csv; do
    /usr/bin/time -v "$rotcal" run "$fmt" --out "out_${fmt}_block" --quiet 2> "${fmt}_block.time" >/dev/null
    /usr/bin/time -v "$rotcal" run "$fmt" --out "out_${fmt}_whole" --quiet --config whole.toml 2> "${fmt}_whole.time" >/dev/null
done
for f in *.time; do
    echo "$f: $(grep -E 'Maximum resident' "$f" | awk '{print $NF}') KiB peak," \
         "$(grep -E '(User|System) time' "$f" | awk '{s += $NF} END {print s}') s CPU"
done
for fmt in mcap csv; do
    echo "== $fmt: block by block against read whole"
    "$python" "$here/compare_outputs.py" "out_${fmt}_block" "out_${fmt}_whole"
done
