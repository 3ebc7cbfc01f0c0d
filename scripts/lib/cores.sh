# Sourced by the other libraries here: the machine's cores, whatever OMP_NUM_THREADS says.
cores() { env -u OMP_NUM_THREADS -u OMP_THREAD_LIMIT nproc; }  # GNU nproc obeys OMP_NUM_THREADS
