/* The candidate scan's AVX2 path for the portable x86 build, compiled for x86-64-v3 (AVX2) and
 * entered only on such a CPU (ft_fx_scan_select in scan.c). */
#define FT_SCAN_VARIANT
#include "scan.c"
