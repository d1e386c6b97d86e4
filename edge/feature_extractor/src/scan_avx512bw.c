/* The candidate scan's AVX-512BW path for the portable x86 build, compiled for x86-64-v4
 * (AVX-512) and entered only on such a CPU (ft_fx_scan_select in scan.c). */
#define FT_SCAN_VARIANT
#include "scan.c"
