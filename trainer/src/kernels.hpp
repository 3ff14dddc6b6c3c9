// Backward-pass kernels of the trainer. Internal to trainer/.
#pragma once

#include <cstddef>

namespace lsnif::trainer::detail {

// dWt[i][o] += sum_r X[r*ldx + i] * G[r*outp + o] for i < in, o < outp (outp multiple
// of 16). The weight-gradient GEMM (X^T G) in the layout the forward kernel reads.
void outer_accumulate(const float* X, std::size_t n, std::size_t in, std::size_t ldx, const float* G,
                      std::size_t outp, float* dWt);

// C[r*outp + o] = bias[o] + sum_i A[r*lda + i] * Wt[i*outp + o] for r < n, o < outp (outp a
// multiple of 16, no activation): format::dense_layer's product for narrow layers such as
// the output layer (outp = 16), where dense_layer's 4-vector blocking drops to a generic
// loop. Same operation order per element (bias, then one FMA per input in order), so the
// results equal dense_layer's bit for bit. Needs AVX-512F; returns false (and computes
// nothing) without it.
bool dense_narrow(const float* A, std::size_t n, std::size_t in, std::size_t lda, const float* Wt,
                  const float* bias, std::size_t outp, float* C);

}  // namespace lsnif::trainer::detail
