// SHA-256 (FIPS 180-4) through OpenSSL's libcrypto. Scenes are content-addressed by the
// lowercase hex digest of their bytes.
#pragma once

#include <cstddef>
#include <memory>
#include <string>

namespace rf {

class Sha256 {
 public:
  Sha256();
  ~Sha256();
  Sha256(const Sha256&) = delete;
  Sha256& operator=(const Sha256&) = delete;
  void update(const void* data, size_t size);
  // Lowercase hex of the digest; the object cannot be updated afterwards.
  std::string final_hex();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

std::string sha256_hex(const std::string& bytes);
// Digest of a file's bytes; throws std::runtime_error naming the file if it cannot be read.
std::string sha256_file_hex(const std::string& path);
// True for 64 lowercase hex characters.
bool is_sha256_hex(const std::string& s);

}  // namespace rf
