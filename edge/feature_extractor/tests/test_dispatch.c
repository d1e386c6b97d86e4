/* The portable x86 build's choice of vector path (src/scan.c, ft_fx_scan_select): the widest this
 * CPU runs, judged here apart from the library (CPUID and the OS's saved register state read
 * directly, not libgcc's flags the library uses), and every path it cannot run refused when forced.
 * That the chosen path gives the same results as the others is checked by test_scan (each path
 * against the plain per-pixel scan) and by fx_compare (this build against the build without the
 * wider paths, and against the native build). */
#include "flytrack/features.h"
#include "fx_internal.h"

#include <cpuid.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>

/* x86-64-v3 (the AVX2 path) and v4 (the AVX-512BW path) usable: the CPU has every extension of the
 * level (CPUID) and the OS saves their registers (XCR0: SSE and AVX state, plus the opmask and
 * upper ZMM state for AVX-512). */
static void cpu_levels(int *v3, int *v4) {
    unsigned a, b, c, d, c1, b7, xc;
    *v3 = *v4 = 0;
    if (!__get_cpuid(1, &a, &b, &c1, &d) || !(c1 & (1u << 27))) /* OSXSAVE */
        return;
    uint32_t lo, hi;
    __asm__ volatile("xgetbv" : "=a"(lo), "=d"(hi) : "c"(0));
    if (!__get_cpuid_count(7, 0, &a, &b7, &c, &d) || !__get_cpuid(0x80000001u, &a, &b, &xc, &d))
        return;
    const unsigned v3_c1 = 1u << 12 | 1u << 22 | 1u << 28 | 1u << 29; /* FMA MOVBE AVX F16C */
    const unsigned v3_b7 = 1u << 3 | 1u << 5 | 1u << 8;               /* BMI1 AVX2 BMI2 */
    const unsigned v4_b7 = 1u << 16 | 1u << 17 | 1u << 28 | 1u << 30 | 1u << 31; /* F DQ CD BW VL */
    *v3 = (lo & 0x6u) == 0x6u && (c1 & v3_c1) == v3_c1 && (b7 & v3_b7) == v3_b7 &&
          (xc & (1u << 5)); /* LZCNT */
    *v4 = *v3 && (lo & 0xe6u) == 0xe6u && (b7 & v4_b7) == v4_b7;
}

int main(void) {
    int has2, has512;
    cpu_levels(&has2, &has512);
    const char *want = has512 ? "avx512bw" : has2 ? "avx2" : "generic";
    ft_fx_params p;
    ft_fx_params_default(&p, 640, 48, FT_FX_MONO8);
    ft_fx *fx;
    if (ft_fx_create(&p, sizeof p, &fx) != FT_FX_OK) {
        fprintf(stderr, "test_dispatch: ft_fx_create failed\n");
        return 1;
    }
    int failures = 0;
    const char *got = ft_fx_debug_scan_path(fx);
    if (strcmp(got, want)) {
        fprintf(stderr, "test_dispatch: the library chose %s, this CPU's widest is %s\n", got,
                want);
        failures++;
    }
    /* Forcing: a path this CPU runs is taken, one it lacks (or a wrong name) is refused. */
    static const char *const names[] = {"avx512bw", "avx2", "generic", "sse9"};
    const int runs[] = {has512, has2, 1, 0};
    for (int i = 0; i < 4; i++) {
        int ok = ft_fx_debug_scan_force(fx, names[i]) == 0;
        if (ok != runs[i] || (ok && strcmp(ft_fx_debug_scan_path(fx), names[i]))) {
            fprintf(stderr, "test_dispatch: forcing %s %s\n", names[i],
                    ok ? "was taken, or set another path" : "was refused");
            failures++;
        }
    }
    ft_fx_destroy(fx);
    if (failures)
        return 1;
    printf("test_dispatch: this CPU's widest path %s chosen; paths it lacks refused\n", got);
    return 0;
}
