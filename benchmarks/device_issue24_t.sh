#!/bin/bash
# Issue 24: the 8 generators x 30 draws x 40 sessions with the Student-t likelihood (df 4), one process each.
R=/tmp/res; mkdir -p $R
export PYTHONPATH=$PWD JAX_PLATFORMS=cpu MPLBACKEND=Agg PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1
export XLA_FLAGS="--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
T=${1:-400}
for g in gauss t3 offsets_small cross_only uniform heavy temp_drift correlated; do
  timeout $T python3 benchmarks/bench_hierarchical.py generators --draws 30 --sessions 40 --likelihood student_t --df 4 --generator $g > $R/gen_$g.txt 2>&1 &
done
wait
tar czf $OUT/res_t.tgz -C $R .
grep -h "| hier \|Error" $R/gen_*.txt
