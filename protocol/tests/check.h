/* Minimal test helpers for the protocol tests: count failures, print where they happened. */
#ifndef FT_TEST_CHECK_H
#define FT_TEST_CHECK_H

#include <stdio.h>

static int ft_test_failures;
static int ft_test_checks;

#define CHECK(cond)                                                                                \
    do {                                                                                           \
        ft_test_checks++;                                                                          \
        if (!(cond)) {                                                                             \
            ft_test_failures++;                                                                    \
            fprintf(stderr, "%s:%d: CHECK failed: %s\n", __FILE__, __LINE__, #cond);               \
        }                                                                                          \
    } while (0)

#define CHECK_ERR(expr, want)                                                                      \
    do {                                                                                           \
        ft_err got_ = (expr);                                                                      \
        ft_test_checks++;                                                                          \
        if (got_ != (want)) {                                                                      \
            ft_test_failures++;                                                                    \
            fprintf(stderr, "%s:%d: %s gave %s, want %s\n", __FILE__, __LINE__, #expr,             \
                    ft_err_name(got_), ft_err_name(want));                                         \
        }                                                                                          \
    } while (0)

static inline int ft_test_report(const char *name) {
    printf("%s: %d checks, %d failed\n", name, ft_test_checks, ft_test_failures);
    return ft_test_failures ? 1 : 0;
}

#endif
