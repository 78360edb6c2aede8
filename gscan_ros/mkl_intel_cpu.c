/* MKL vendor shim: preloaded (LD_PRELOAD) into a process whose torch does its float
 * matmuls with MKL, it answers MKL's "is this an Intel CPU?" with yes. MKL then picks its
 * kernels by the CPU's features (AVX2, AVX-512) as it does on Intel CPUs, instead of its
 * generic path for other vendors' CPUs. Built by `make setup`; used through
 * gscan_ros.runtime.mkl_shim_env (figures: docs/results.md, "Engine settings"). */
int mkl_serv_intel_cpu_true(void) { return 1; }
