#!/bin/bash
# svr bids on a SLURM cluster: one participant per array task.
#
#   sbatch --array=1-40 svr-bids-array.sh --masks-dir study-masks/
#
# Task N reconstructs the participant in row N of participants.tsv (after its header). Options
# after the script's name go to svr bids; BIDS_DIR and OUTPUT_DIR name the dataset and the
# derivatives folder. Resubmitting the array after a failure redoes only the participants
# without outputs; run `svr bids "$BIDS_DIR" "$OUTPUT_DIR" group` once all tasks are done.
#SBATCH --job-name=svr-bids
#SBATCH --cpus-per-task=4
#SBATCH --mem=16G
#SBATCH --time=01:00:00
set -euo pipefail
BIDS_DIR=${BIDS_DIR:-study}
OUTPUT_DIR=${OUTPUT_DIR:-study-svr}
: "${SLURM_ARRAY_TASK_ID:?run this script as a SLURM job array (sbatch --array=1-N)}"
label=$(awk -F'\t' -v row=$((SLURM_ARRAY_TASK_ID + 1)) 'NR == row { print $1 }' \
    "$BIDS_DIR/participants.tsv")
if [ -z "$label" ]; then
    echo "svr-bids-array: no participant in row $SLURM_ARRAY_TASK_ID of $BIDS_DIR/participants.tsv" >&2
    exit 1
fi
exec svr bids "$BIDS_DIR" "$OUTPUT_DIR" participant --participant-label "$label" "$@"
