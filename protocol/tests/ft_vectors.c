/* ft_vectors <vectors dir>: checks the C codec against every golden vector (SPEC section 5).
 * Prints each failure, then exactly one line `C codec: N vectors passed, M failed`; exits non-zero
 * when M > 0 or N == 0. */
#define _POSIX_C_SOURCE 200809L
#include "vector_runner.h"

int main(int argc, char **argv) {
    vr_counts c = {0, 0, NULL};
    c.log = stdout;
    if (argc != 2) {
        fprintf(stderr, "usage: %s <vectors dir>\n", argv[0]);
        return 2;
    }
    vr_run_dir(&c, argv[1]);
    printf("C codec: %d vectors passed, %d failed\n", c.passed, c.failed);
    return (c.failed > 0 || c.passed == 0) ? 1 : 0;
}
