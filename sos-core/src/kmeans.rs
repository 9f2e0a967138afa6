//! Seeded k-means with k-means++ initialisation and restarts.
